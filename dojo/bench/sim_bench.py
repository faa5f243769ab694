"""`dojo bench sim`: simulation throughput of the backend the user names.

`backend=mujoco` measures the CPU backend alone (what a machine without a GPU runs; JAX is never imported).
`backend=mjx` (the default) measures the batched backend; one workload, three ways to run it:
- `heterogeneous`: every bucket of every task in one process, all buckets of a tick in one jitted call;
- `homogeneous`: the same buckets with the same batch sizes, one bucket's batch at a time (its own jitted call),
  one after another: what a batched simulator without heterogeneous parallelism does with a task mix;
- `cpu`: the `mujoco` backend (`dojo.backends.mujoco.bench.measure_cpu`) on the same plans;
- `merged` (asked for by name): `heterogeneous` over buckets merged across tasks (`make_buckets(merge=True)`, with
  the backend config's `merge_growth`: tasks share a structure where the scenes allow it and the merged model stays
  within that growth of its largest task's), its bucket count, sizes and models beside its rates;
- `streams` (by name; MuJoCo Warp): every bucket's physics on its own CUDA stream, concurrently (`mjx.streams`),
  with the same graphs on one stream beside it;
- `merged_streams` (by name; MuJoCo Warp): `streams` over the merged buckets: fewer, larger launches, overlapped;
- `alone` (by name): each task by itself at the whole batch, on the engine of the mix (`streams` when that is
  measured, else the jitted one), and `ideal_mix`, the mix's rate were each task to run at its own full-batch
  rate for its share of the batch: a task whose scenes cost five times another's per step costs so in any batch,
  so an engine passes it only by running tasks faster side by side than alone (the mix's `X_over_ideal_mix` is
  how close an engine comes).

With `backend.streams=true` the engine of `heterogeneous` and `merged` runs its physics on Warp's lanes between two
jitted halves (`dojo run`'s engine under that setting, with `backend.merge=true` for `merged`), and their figures
add `split_tick_ms`: the median milliseconds of a timed tick's first half, lanes and second half, each waited for,
and `lane_ms`: each lane's tick alone (its tasks, environments, median ms), as do `streams` and `merged_streams`:
a concurrent tick as long as its slowest lane wants that bucket smaller, one as long as the lanes' sum over their
overlap wants fewer graph nodes. `kernel_times=N` (NVIDIA GPU) adds `kernel_ms`: per lane, one more tick run
launch by launch with every kernel timed, its GPU total and its N costliest kernels (`mjx.kernel_timing`).

The protocol's workload (50 episodes per task, all at once) is `num_envs` = 50 x the tasks: there each bucket is
small, and `homogeneous` pays a whole launch per bucket that a GPU at a few dozen worlds leaves idle.

The batch (`num_envs`) is shared among buckets in proportion to their plans (episodes); environment i of a
bucket runs plan i mod n. Physics only: controls are each plan's initial controls with a +-0.1 rad swing of the
arm joints that alternates every control step, so arms move and servos work; no predicates, no observations.
Two counts, never mixed: `interactions_per_s` counts control steps (one action applied in one environment, at
the plans' control rate), `physics_steps_per_s` counts physics steps (one `mj_step` of one environment; a control
step is `substeps_per_interaction` of them). The first tick (compilation) and `warmup` ticks are excluded from
the timings and reported apart.
"""

from __future__ import annotations

import gc
import logging
import math
import os
import time
from collections import Counter, defaultdict
from importlib.metadata import version
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Mapping, Sequence

import mujoco
import numpy as np

if TYPE_CHECKING:
    import jax

    from dojo.backends.mjx.bucket import Bucket
    from dojo.backends.mjx.sharding import Placement

SWING = 0.1
MJX_MODES = ("heterogeneous", "homogeneous", "cpu", "streams", "merged", "merged_streams", "alone")
"""`streams` and `merged_streams` (`mjx.streams`: each bucket on its own CUDA stream, physics only) need MuJoCo
Warp, `merged` pays only on a GPU (README, speed: 1.18x the separate buckets at 16,384 H100 environments, slower
on a CPU), and `alone` measures every task once more: all four are asked for by name."""
STREAM_MODES = frozenset({"streams", "merged_streams"})
COUNTS = {"interactions": "control steps: one action applied in one environment",
          "physics_steps": "mj_step calls of one environment (substeps_per_interaction per control step)"}
log = logging.getLogger(__name__)


def load_plans(cfg: dict[str, Any]) -> list[Any]:
    """Plans from `cfg['plans']` (a folder of plan files or `dojo compile`'s output, filtered by `tasks`, at most
    `episodes` a task when given), else compiled: `episodes` standard-setting seeds of each task in `tasks` (every
    built-in task when empty)."""
    from dojo.compiler.plan import Plan, compile_plan
    from dojo.compiler.spec_library import SpecLibrary
    from dojo.compiler.suite_compile import plan_files

    tasks = list(cfg.get("tasks") or [])
    if cfg.get("plans"):
        folder = Path(cfg["plans"])
        found = [Plan.load(p) for p in plan_files(folder)]
        plans = [p for p in found if not tasks or p.task in tasks]
        if not plans:
            # A bench of nothing would fail later, far from the cause (a folder gone or mistyped, a task filter
            # that matches no plan in it); say which.
            what = f"no plan of {tasks}" if found else "no plan files (*.json)"
            raise ValueError(f"plans={folder}: {what} in {folder.resolve()}")
        per_task, count = int(cfg.get("episodes") or 0), Counter[str]()
        if per_task:
            kept = []
            for plan in plans:
                if count[plan.task] < per_task:
                    kept.append(plan)
                    count[plan.task] += 1
            plans = kept
        return plans
    library = SpecLibrary.load([Path(p) for p in cfg.get("packages", [])])
    tasks = tasks or sorted(s.id for s in library.of_kind("task"))
    return [compile_plan(library, library.get("task", t), "standard", seed)
            for t in tasks for seed in range(int(cfg.get("episodes") or 2))]


def split_batch(buckets: Sequence[Bucket], num_envs: int) -> list[int]:
    """Environments per bucket, proportional to its plans, at least one each, summing to num_envs."""
    if num_envs < len(buckets):
        raise ValueError(f"num_envs={num_envs} is smaller than the number of buckets ({len(buckets)})")
    weights = np.asarray([len(b.members) for b in buckets], dtype=float)
    sizes = np.maximum(1, np.floor(num_envs * weights / weights.sum())).astype(int)
    for k in np.argsort(-weights)[: num_envs - int(sizes.sum())]:
        sizes[k] += 1
    return [int(s) for s in sizes]


def _controls(bucket: Bucket, size: int) -> tuple[jax.Array, jax.Array]:
    """The two alternating control batches of a bucket (on the device)."""
    import jax.numpy as jnp

    base = np.stack([bucket.members[i % len(bucket.members)].ctrl for i in range(size)]).astype(np.float32)
    arm = np.zeros(bucket.model.nu, np.float32)
    robot = bucket.members[0].plan.robot
    names = [mujoco.mj_id2name(bucket.model, mujoco.mjtObj.mjOBJ_ACTUATOR, a) for a in range(bucket.model.nu)]
    arm[[k for k, n in enumerate(names) if n not in robot.get("gripper_actuators", ())]] = SWING
    return jnp.asarray(base + arm), jnp.asarray(base - arm)


def _run(buckets: Sequence[Bucket], sizes: Sequence[int], impl: str, steps: int, warmup: int,
         placement: Placement | None = None, graph_mode: object | None = None, streams: bool = False,
         kernels: int = 0) -> dict[str, Any]:
    """Build one engine over `buckets` (its batches split over `placement`'s devices, its Warp calls captured as
    `graph_mode` says, its physics on streams with `streams`: `backend.streams`), compile, warm up, and time
    `steps` ticks; on streams, each lane alone after them (`lane_ms`, and with `kernels` > 0 its costliest
    kernels, `kernel_ms`)."""
    import jax

    from dojo.backends.mjx.batch import Engine
    from dojo.backends.mjx.streams import lane_figures

    start = time.perf_counter()
    engine = Engine(buckets, sizes, impl, placement=placement, graph_mode=graph_mode, streams=streams)
    # the flags on the host, as `dojo run`'s loop hands them over each tick; the controls on the device
    members = [(np.arange(n) % len(b.members)).astype(np.int32) for b, n in zip(buckets, sizes)]
    ones = [np.ones(n, bool) for n in sizes]
    zeros = [np.zeros(n, bool) for n in sizes]
    swings = [_controls(b, n) for b, n in zip(buckets, sizes)]
    engine.tick(members, ones, zeros, [s[0] for s in swings])
    jax.block_until_ready(engine.data)
    compile_s = time.perf_counter() - start
    log.info("%d bucket(s), %d envs: engine built and first tick compiled in %.1f s", len(buckets), sum(sizes),
             compile_s)
    for k in range(warmup):
        engine.tick(members, zeros, ones, [s[k % 2] for s in swings])
    jax.block_until_ready(engine.data)
    if streams:
        engine.split_ms = {"first_half": [], "lanes": [], "second_half": []}
    start = time.perf_counter()
    for k in range(steps):
        engine.tick(members, zeros, ones, [s[k % 2] for s in swings])
    jax.block_until_ready(engine.data)
    elapsed = time.perf_counter() - start
    lanes = lane_figures(engine, kernels)  # each lane alone (none without streams), before the overflow check
    engine.check_overflow()  # dropped contacts make a faster, wrong simulation: no figures for it
    envs = sum(sizes)
    substeps = sum(n * b.n_substeps for b, n in zip(buckets, sizes)) / envs
    out = {"seconds": elapsed, "setup_s": compile_s, "interactions": envs * steps,
           "physics_steps": envs * steps * substeps, "compilations": engine.compilations(),
           "qpos": [np.asarray(d.qpos) for d in engine.data], **lanes}
    if engine.split_ms is not None:  # where a split tick's time goes: medians of the timed ticks
        out["split_tick_ms"] = {part: float(np.median(kept)) for part, kept in engine.split_ms.items()}
    # The engine's jitted tick refers back to it (a cycle), so only the garbage collector frees its programs: now,
    # not while the next engine's Warp call captures a CUDA graph, which the freeing would break (H100).
    del engine
    gc.collect()
    return out


def _streams(buckets: Sequence[Bucket], sizes: Sequence[int], steps: int, warmup: int,
             serial: bool = True, kernels: int = 0) -> dict[str, Any]:
    """The buckets' physics on one CUDA stream each, against the same graphs on one stream unless `serial` is
    False (`mjx.streams`; `kernels`: as `measure_streams` takes it)."""
    from dojo.backends.mjx.streams import measure_streams

    controls = [[np.asarray(c) for c in _controls(b, n)] for b, n in zip(buckets, sizes)]
    return measure_streams(buckets, sizes, controls, steps, warmup, serial=serial, kernels=kernels)


def _alone(buckets: Sequence[Bucket], sizes: Sequence[int], impl: str, steps: int, warmup: int,
           placement: Placement, graphs: object | None, on_streams: bool) -> dict[str, Any]:
    """Each task's buckets by themselves at the mix's whole batch, and the mix's best from their rates
    (`ideal_mix`)."""
    total = sum(sizes)
    by_task: dict[tuple[str, ...], list[tuple[Bucket, int]]] = defaultdict(list)
    for bucket, n in zip(buckets, sizes):
        by_task[bucket.tasks].append((bucket, n))
    per_task = {}
    for tasks, own in sorted(by_task.items()):
        own_buckets = [b for b, _ in own]
        own_sizes = [placement.padded(n) for n in split_batch(own_buckets, total)]
        rates = (_streams(own_buckets, own_sizes, steps, warmup, serial=False) if on_streams else
                 _rates([_run(own_buckets, own_sizes, impl, steps, warmup, placement, graphs)]))
        per_task[",".join(tasks)] = {"share": sum(n for _, n in own) / total, "num_envs": sum(own_sizes),
                                     **{k: rates[k] for k in ("interactions_per_s", "physics_steps_per_s",
                                                              "setup_s")}}
    return {"per_task": per_task, "ideal_mix": ideal_mix(per_task.values())}


def ideal_mix(tasks: Iterable[Mapping[str, float]]) -> dict[str, float]:
    """The mix's rate were every task to run at its own full-batch rate for its share of the batch: a share s_t of
    the environments at i_t interactions/s takes s_t / i_t of a second per interaction of the batch, so the mix
    then runs at 1 / sum(s_t / i_t), with the shares' mean of the tasks' sub-steps per interaction.
    Measured on the 24 simulation tasks (H200, 2026-11-28, 16,384 environments, streams) it is 46% of
    `stack_blocks` alone: the scenes of a mix, not only its engine, decide how near one task it runs."""
    seconds = substeps = 0.0
    for t in tasks:
        seconds += t["share"] / t["interactions_per_s"]
        substeps += t["share"] * t["physics_steps_per_s"] / t["interactions_per_s"]
    return {"interactions_per_s": 1.0 / seconds, "physics_steps_per_s": substeps / seconds}


def _device_counts(devices: Any) -> list[int]:
    """`backend.devices` as the sorted device counts to measure: one count, `all`, or a list such as [1,4]."""
    from dojo.backends.mjx.sharding import local_devices

    listed = devices if isinstance(devices, (list, tuple)) else [devices]
    return sorted({len(local_devices(n)) for n in listed})


def _by_devices(runs: dict[int, dict[str, Any]]) -> dict[str, Any]:
    """The heterogeneous mix per device count, each with its speedup over the fewest devices and how far its final
    positions are from that run's (0.0: the same physics bit for bit)."""
    first = min(runs)
    base = _rates([runs[first]])["interactions_per_s"]
    out = {}
    for n, run in sorted(runs.items()):
        rates = _rates([run])
        diff = max(float(np.max(np.abs(a - b), initial=0.0)) for a, b in zip(run["qpos"], runs[first]["qpos"]))
        out[str(n)] = {**rates, f"speedup_over_{first}": rates["interactions_per_s"] / base,
                       f"max_qpos_difference_from_{first}": diff}
    return out


def _models(buckets: Sequence[Bucket]) -> list[dict[str, Any]]:
    """What each bucket simulates per environment (the sizes a merge trades against the bucket count)."""
    return [{"tasks": list(b.tasks), "plans": len(b.members), "nv": b.model.nv, "ngeom": b.model.ngeom,
             "nbody": b.model.nbody} for b in buckets]


def _rates(runs: Sequence[dict[str, float]]) -> dict[str, float]:
    seconds = sum(r["seconds"] for r in runs)
    out = {"interactions_per_s": sum(r["interactions"] for r in runs) / seconds,
           "physics_steps_per_s": sum(r["physics_steps"] for r in runs) / seconds,
           "seconds": seconds, "setup_s": sum(r["setup_s"] for r in runs),
           "compilations": int(sum(r["compilations"] for r in runs))}
    if len(runs) == 1:  # one engine: where its ticks' time went, if it split them (`backend.streams`)
        out.update({k: runs[0][k] for k in ("split_tick_ms", "lane_ms", "kernel_ms") if k in runs[0]})
    return out


def _peak_memory() -> int | None:
    import jax

    stats = jax.devices()[0].memory_stats() or {}
    return stats.get("peak_bytes_in_use")


def _modes(backend: str, modes: Sequence[str] | None) -> tuple[str, ...]:
    """The modes to measure: the CPU alone for backend=mujoco, else the given subset of MJX_MODES (all three)."""
    if backend not in ("mjx", "mujoco"):
        raise ValueError(f"bench sim measures backend mjx or mujoco; got backend {backend!r}")
    chosen = tuple(modes or (("cpu",) if backend == "mujoco" else MJX_MODES[:3]))
    unknown = [m for m in chosen if m not in MJX_MODES]
    if unknown:
        raise ValueError(f"unknown bench sim mode(s) {unknown}; choose among {list(MJX_MODES)}")
    if backend == "mujoco" and chosen != ("cpu",):
        raise ValueError("backend=mujoco measures the CPU backend alone; heterogeneous and homogeneous are modes "
                         "of backend=mjx")
    return chosen


def bench_sim(cfg: dict[str, Any]) -> dict[str, Any]:
    """Measure and return the figures of `dojo bench sim` (one JSON object).

    cfg keys: `num_envs` (total batch), `steps` (timed control steps), `warmup` (untimed ticks after the
    compiling one, default 3), `tasks` (ids; empty = all), `plans` (folder of compiled plans; else `episodes`
    plans per task are compiled), `episodes`, `backend: {name, impl, devices}` (name `mjx` or `mujoco`; impl `auto`,
    `jax` or `warp`; devices a count, `all`, or a list of counts such as [1,4], each measured on the heterogeneous
    mix in this one run and reported under `by_devices`, batches padded for the most devices; `graph_mode`, MJX's
    CUDA graph capture of Warp calls; `streams`, the heterogeneous engine's physics on CUDA streams),
    `dof_quantum` (every bucket's DoFs rounded up to a multiple of it, `dof_rounding`: fewer Warp kernels to
    compile, larger models; 1: off), `modes` (subset of MJX_MODES;
    backend=mujoco is `cpu` alone), `cpu_envs`, `cpu_steps` (the size of the CPU baseline of an mjx measurement),
    `cache_dir` (persistent compilation cache).
    """
    backend = cfg.get("backend") or {}
    name = str(backend.get("name", "mjx"))
    modes = _modes(name, cfg.get("modes"))
    if modes == ("cpu",):
        if name == "mujoco":  # the backend named: its sizes are the command's num_envs and steps
            return bench_cpu(cfg, int(cfg.get("num_envs", 8)), int(cfg.get("steps", 10)))
        return bench_cpu(cfg, int(cfg.get("cpu_envs", 8)), int(cfg.get("cpu_steps", 10)))
    return _bench_mjx(cfg, backend, modes)


def bench_cpu(cfg: dict[str, Any], num_envs: int, steps: int) -> dict[str, Any]:
    """The mujoco backend alone, on plans compiled for it: what `dojo run` steps on a machine without a GPU."""
    from dojo.backends.mujoco.bench import measure_cpu

    start = time.perf_counter()
    plans = load_plans(cfg)
    log.info("%d plans (%.1f s)", len(plans), time.perf_counter() - start)
    cpu = measure_cpu(plans, num_envs, steps, resets=1)
    substeps = float(np.mean([p.n_substeps for p in plans]))
    out = {"what": "sim", "backend": "mujoco", "num_envs": num_envs, "steps": steps, "threads": cpu["threads"],
           "cpus": os.cpu_count(), "tasks": sorted({p.task for p in plans}), "episodes": len(plans),
           "mujoco": mujoco.__version__, "counts": COUNTS, "substeps_per_interaction": substeps,
           **_cpu_figures(cpu, substeps)}
    if len(out["tasks"]) > 1:  # each task's scenes alone too, in the same run: a heavy scene (many bodies) shows
        out["per_task"] = {task: _task_rate([p for p in plans if p.task == task], num_envs, steps)
                           for task in out["tasks"]}
    if len(out["tasks"]) == 1:  # one scene: the backend's cost over plain mj_step of it, per CPU second
        bare = cpu["raw_mj_step_per_cpu_s"] / substeps
        out["bare_physics"] = {"mj_step_per_cpu_s": cpu["raw_mj_step_per_cpu_s"], "interactions_per_cpu_s": bare}
        out["overhead_over_bare_physics"] = 1.0 - cpu["interactions_per_cpu_s"] / bare
    return out


def _task_rate(plans: Sequence[Any], num_envs: int, steps: int) -> dict[str, float]:
    """Control steps and physics steps per CPU second of one task's plans on the mujoco backend."""
    from dojo.backends.mujoco.bench import measure_cpu

    rate = measure_cpu(plans, num_envs, steps, resets=1)["interactions_per_cpu_s"]
    return {"interactions_per_cpu_s": rate,
            "physics_steps_per_cpu_s": rate * float(np.mean([p.n_substeps for p in plans]))}


def _cpu_figures(cpu: dict[str, Any], substeps: float) -> dict[str, Any]:
    return {"interactions_per_s": cpu["interactions_per_s"], "interactions_per_cpu_s": cpu["interactions_per_cpu_s"],
            "physics_steps_per_s": cpu["interactions_per_s"] * substeps,
            **{k: cpu[k] for k in ("reset_ms_mean", "reset_ms_max", "load_average_1min")}}


def gpu_settings(modes: Sequence[str], engine_streams: bool = False) -> dict[str, str]:
    """The environment the GPU side starts with. JAX's share of the GPU beside the stream engines, which allocate
    through Warp: JAX takes 75% of the GPU when it starts, by default. With stream modes alone JAX holds a few
    control arrays and reserves nothing up front (the 24-task mix merged into 13 buckets at 16,384 environments ran
    out of memory in its second engine on an H100 while JAX held half, 2026-11-28); beside a JAX engine it gets
    half, as it does when the JAX engine's own physics runs on streams (`engine_streams`). Wherever streams run,
    the CUDA driver's hardware queues too (`STREAMS_ENVIRONMENT`); beside a JAX engine, what `backend.streams`
    sets (`ENGINE_STREAMS_ENVIRONMENT`)."""
    from dojo.backends.mjx import ENGINE_STREAMS_ENVIRONMENT, STREAMS_ENVIRONMENT

    if not STREAM_MODES & set(modes):
        return dict(ENGINE_STREAMS_ENVIRONMENT) if engine_streams else {}
    if set(modes) <= STREAM_MODES:
        return {"XLA_PYTHON_CLIENT_PREALLOCATE": "false", **STREAMS_ENVIRONMENT}
    return dict(ENGINE_STREAMS_ENVIRONMENT)


def _bench_mjx(cfg: dict[str, Any], backend: dict[str, Any], modes: tuple[str, ...]) -> dict[str, Any]:
    import jax

    from dojo.backends.mjx import merge_growth
    from dojo.backends.mjx.bucket import make_buckets
    from dojo.backends.mjx.cache import (choose_impl, describe_impl, enable_compilation_cache, graph_mode,
                                         graph_mode_name)
    from dojo.backends.mjx.dof_rounding import round_bucket
    from dojo.backends.mjx.sharding import Placement, local_devices

    on_streams = bool(STREAM_MODES & set(modes))
    engine_streams = backend.get("streams") is True  # auto: the bench's modes say where the physics runs
    for name, value in gpu_settings(modes, engine_streams).items():  # before JAX or Warp starts on the GPU
        os.environ.setdefault(name, value)
    enable_compilation_cache(cfg.get("cache_dir"))
    impl = choose_impl(backend.get("impl"))
    graphs = graph_mode(backend.get("graph_mode"), impl)
    if engine_streams and impl != "warp":
        raise ValueError("backend.streams runs the engine's physics on MuJoCo Warp: it needs backend.impl=warp")
    if on_streams and impl != "warp":
        raise ValueError("bench sim modes 'streams' and 'merged_streams' run MuJoCo Warp: they need "
                         "backend.impl=warp on an NVIDIA GPU")
    kernels = int(cfg.get("kernel_times") or 0)
    if kernels > 0 and not (engine_streams or on_streams):
        raise ValueError("bench sim kernel_times times the lanes of backend.streams=true or of the modes 'streams' "
                         "and 'merged_streams': ask for one of them")
    if kernels > 0 and jax.default_backend() == "cpu":
        raise ValueError("bench sim kernel_times needs an NVIDIA GPU: Warp times kernels with CUDA events")
    log.info("mjx: %s", describe_impl(impl))
    if jax.default_backend() == "cpu" and modes != ("cpu",):
        log.warning("backend=mjx on a CPU: expect minutes of compilation per task; backend=mujoco measures the "
                    "CPU backend")
    steps, warmup = int(cfg.get("steps", 20)), int(cfg.get("warmup", 3))
    start = time.perf_counter()
    plans = load_plans(cfg)
    quantum = int(cfg.get("dof_quantum") or 1)
    buckets = [round_bucket(b, quantum) for b in make_buckets(plans)]
    log.info("%d plans in %d buckets (%.1f s)", len(plans), len(buckets), time.perf_counter() - start)
    counts = _device_counts(backend.get("devices"))
    placements = {n: Placement.over(local_devices(n), impl) for n in counts}
    widest = placements[counts[-1]]
    sizes = [widest.padded(n) for n in split_batch(buckets, int(cfg.get("num_envs", len(buckets))))]
    out: dict[str, Any] = {
        "what": "sim", "backend": "mjx", "impl": impl, "num_envs": sum(sizes), "steps": steps,
        "tasks": sorted({p.task for p in plans}), "episodes": len(plans), "buckets": len(buckets),
        "bucket_sizes": sizes, "device": jax.devices()[0].device_kind, "platform": jax.devices()[0].platform,
        "jax": jax.__version__, "mujoco": mujoco.__version__, "mujoco_mjx": version("mujoco-mjx"), "counts": COUNTS,
        "graph_mode": graph_mode_name(graphs), "engine_streams": engine_streams,
        "dof_quantum": quantum, "bucket_nv": [int(b.model.nv) for b in buckets],
    }
    out["devices"] = widest.count
    if "heterogeneous" in modes:
        runs = {n: _run(buckets, sizes, impl, steps, warmup, placements[n], graphs, engine_streams, kernels)
                for n in counts}
        out["heterogeneous"] = _rates([runs[counts[-1]]])
        if len(counts) > 1:
            out["by_devices"] = _by_devices(runs)
        peak = _peak_memory()
        out["peak_device_bytes_per_env"] = None if peak is None else peak / sum(sizes)
    if "homogeneous" in modes:
        out["homogeneous"] = _rates([_run([b], [n], impl, steps, warmup, widest, graphs)
                                     for b, n in zip(buckets, sizes)])
    if "streams" in modes:
        out["streams"] = _streams(buckets, sizes, steps, warmup, kernels=kernels)
    if {"merged", "merged_streams"} & set(modes):
        start = time.perf_counter()
        growth = merge_growth(backend.get("merge_growth"))
        merged = [round_bucket(b, quantum) for b in make_buckets(plans, merge=True, growth=growth)]
        merge_s = time.perf_counter() - start
        merged_sizes = [widest.padded(n) for n in split_batch(merged, sum(sizes))]
        about = {"buckets": len(merged), "bucket_sizes": merged_sizes, "padding_s": merge_s,
                 "growth": growth if math.isfinite(growth) else "inf", "models": _models(merged)}
        if "merged" in modes:
            out["merged"] = {**about, **_rates([_run(merged, merged_sizes, impl, steps, warmup, widest, graphs,
                                                     engine_streams, kernels)])}
        if "merged_streams" in modes:
            out["merged_streams"] = {**about, **_streams(merged, merged_sizes, steps, warmup, kernels=kernels)}
    if "alone" in modes:
        engine = "streams" if "streams" in modes else "heterogeneous"
        out["alone"] = {"engine": engine, **_alone(buckets, sizes, impl, steps, warmup, widest, graphs,
                                                     on_streams=engine == "streams")}
    if "cpu" in modes:
        from dojo.backends.mujoco.bench import measure_cpu

        cpu_envs, cpu_steps = int(cfg.get("cpu_envs", 8)), int(cfg.get("cpu_steps", 10))
        cpu = measure_cpu(plans, cpu_envs, cpu_steps, resets=1)
        substeps = float(np.mean([p.n_substeps for p in plans]))
        out["cpu"] = {"backend": "mujoco", "num_envs": cpu_envs, "steps": cpu_steps, "threads": cpu["threads"],
                      **_cpu_figures(cpu, substeps)}
    out["ratios"] = bench_ratios(out)
    return out


def bench_ratios(out: dict[str, Any]) -> dict[str, float]:
    """Each measured way over the others it is compared with, by interactions per second. The stream modes are
    also set against the one-stream run of the separate buckets (`streams`' `serial`: every bucket's graphs one
    after another, the homogeneous mode of the Warp engine), so that one run of `modes=[streams,merged_streams]`
    answers "the mix as one batch against its buckets in turn" even where the jitted `homogeneous`, a compile per
    bucket, is too slow to set up (the protocol's 222 buckets)."""
    ratios = {}
    for a, b in (("heterogeneous", "homogeneous"), ("heterogeneous", "cpu"), ("homogeneous", "cpu"),
                 ("streams", "homogeneous"), ("streams", "heterogeneous"), ("merged", "heterogeneous"),
                 ("merged", "homogeneous"), ("merged_streams", "homogeneous"), ("merged_streams", "streams")):
        if a in out and b in out:
            ratios[f"{a}_over_{b}"] = out[a]["interactions_per_s"] / out[b]["interactions_per_s"]
    if "streams" in out:
        for a in ("streams", "merged_streams"):
            if a in out:
                ratios[f"{a}_over_streams_serial"] = (out[a]["interactions_per_s"]
                                                      / out["streams"]["serial"]["interactions_per_s"])
    if "alone" in out and out["alone"]["engine"] in out:
        ratios[f"{out['alone']['engine']}_over_ideal_mix"] = (out[out["alone"]["engine"]]["interactions_per_s"]
                                                              / out["alone"]["ideal_mix"]["interactions_per_s"])
    return ratios
