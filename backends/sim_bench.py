"""`dojo bench sim`: physics throughput of the batched backend, heterogeneous against homogeneous, and the CPU one.

One workload, three ways to run it:
- `heterogeneous`: every bucket of every task in one process, all buckets of a tick in one jitted call;
- `homogeneous`: the same buckets with the same batch sizes, one bucket's batch at a time (its own jitted call),
  one after another: what a batched simulator without heterogeneous parallelism does with a task mix;
- `cpu`: the `mujoco` backend (`dojo.backends.mujoco.bench.measure_cpu`) on the same plans.

The batch (`num_envs`) is shared among buckets in proportion to their plans (episodes); environment i of a
bucket runs plan i mod n. Physics only: controls are each plan's initial controls with a +-0.1 rad swing of the
arm joints that alternates every control step, so arms move and servos work; no predicates, no observations.
`env_steps_per_s` counts physics steps (one environment, one `mj_step`), `interactions_per_s` control steps.
The first tick (compilation) and `warmup` ticks are excluded from the timings and reported apart.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from importlib.metadata import version
from pathlib import Path
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from .mjx.batch import Engine
from .mjx.bucket import Bucket, make_buckets
from .mjx.cache import choose_impl, enable_compilation_cache

SWING = 0.1
log = logging.getLogger(__name__)


def load_plans(cfg: dict[str, Any]) -> list[Any]:
    """Plans from `cfg['plans']` (a folder of plan files, filtered by `tasks`), else compiled for MJX:
    `episodes` standard-setting seeds of each task in `tasks` (every built-in task when empty)."""
    from dojo.compiler.plan import Plan, compile_plan
    from dojo.compiler.spec_library import SpecLibrary

    tasks = list(cfg.get("tasks") or [])
    if cfg.get("plans"):
        plans = [Plan.load(p) for p in sorted(Path(cfg["plans"]).glob("*.json"))]
        plans = [p for p in plans if not tasks or p.task in tasks]
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
    return [compile_plan(library, library.get("task", t), "standard", seed, backend="mjx")
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
    base = np.stack([bucket.members[i % len(bucket.members)].ctrl for i in range(size)]).astype(np.float32)
    arm = np.zeros(bucket.model.nu, np.float32)
    robot = bucket.members[0].plan.robot
    names = [mujoco.mj_id2name(bucket.model, mujoco.mjtObj.mjOBJ_ACTUATOR, a) for a in range(bucket.model.nu)]
    arm[[k for k, n in enumerate(names) if n not in robot.get("gripper_actuators", ())]] = SWING
    return jnp.asarray(base + arm), jnp.asarray(base - arm)


def _run(buckets: Sequence[Bucket], sizes: Sequence[int], impl: str, steps: int, warmup: int) -> dict[str, float]:
    """Build one engine over `buckets`, compile, warm up, and time `steps` ticks."""
    start = time.perf_counter()
    engine = Engine(buckets, sizes, impl)
    members = [jnp.asarray(np.arange(n) % len(b.members), jnp.int32) for b, n in zip(buckets, sizes)]
    ones = [jnp.ones(n, bool) for n in sizes]
    zeros = [jnp.zeros(n, bool) for n in sizes]
    swings = [_controls(b, n) for b, n in zip(buckets, sizes)]
    engine.tick(members, ones, zeros, [s[0] for s in swings])
    jax.block_until_ready(engine.data)
    compile_s = time.perf_counter() - start
    log.info("%d bucket(s), %d envs: engine built and first tick compiled in %.1f s", len(buckets), sum(sizes),
             compile_s)
    for k in range(warmup):
        engine.tick(members, zeros, ones, [s[k % 2] for s in swings])
    jax.block_until_ready(engine.data)
    start = time.perf_counter()
    for k in range(steps):
        engine.tick(members, zeros, ones, [s[k % 2] for s in swings])
    jax.block_until_ready(engine.data)
    elapsed = time.perf_counter() - start
    envs = sum(sizes)
    substeps = sum(n * b.n_substeps for b, n in zip(buckets, sizes)) / envs
    return {"seconds": elapsed, "setup_s": compile_s, "interactions": envs * steps,
            "env_steps": envs * steps * substeps, "compilations": engine.compilations()}


def _rates(runs: Sequence[dict[str, float]]) -> dict[str, float]:
    seconds = sum(r["seconds"] for r in runs)
    return {"env_steps_per_s": sum(r["env_steps"] for r in runs) / seconds,
            "interactions_per_s": sum(r["interactions"] for r in runs) / seconds,
            "seconds": seconds, "setup_s": sum(r["setup_s"] for r in runs),
            "compilations": int(sum(r["compilations"] for r in runs))}


def _peak_memory() -> int | None:
    stats = jax.devices()[0].memory_stats() or {}
    return stats.get("peak_bytes_in_use")


def bench_sim(cfg: dict[str, Any]) -> dict[str, Any]:
    """Measure and return the figures of `dojo bench sim` (one JSON object).

    cfg keys: `num_envs` (total batch), `steps` (timed control steps), `warmup` (untimed ticks after the
    compiling one, default 3), `tasks` (ids; empty = all), `plans` (folder of compiled plans; else `episodes`
    plans per task are compiled), `episodes`, `backend: {name, impl}` (impl `auto`, `jax` or `warp`),
    `modes` (subset of heterogeneous, homogeneous, cpu), `cpu_envs`, `cpu_steps` (the CPU run's size),
    `cache_dir` (persistent compilation cache).
    """
    enable_compilation_cache(cfg.get("cache_dir"))
    backend = cfg.get("backend") or {}
    if backend.get("name", "mjx") != "mjx":
        raise ValueError(f"bench sim measures the mjx backend against mujoco; got backend {backend.get('name')!r}")
    impl = choose_impl(backend.get("impl"))
    modes = tuple(cfg.get("modes") or ("heterogeneous", "homogeneous", "cpu"))
    steps, warmup = int(cfg.get("steps", 20)), int(cfg.get("warmup", 3))
    start = time.perf_counter()
    plans = load_plans(cfg)
    buckets = make_buckets(plans)
    log.info("%d plans in %d buckets (%.1f s)", len(plans), len(buckets), time.perf_counter() - start)
    sizes = split_batch(buckets, int(cfg.get("num_envs", len(buckets))))
    out: dict[str, Any] = {
        "what": "sim", "backend": "mjx", "impl": impl, "num_envs": sum(sizes), "steps": steps,
        "tasks": sorted({p.task for p in plans}), "episodes": len(plans), "buckets": len(buckets),
        "bucket_sizes": sizes, "device": jax.devices()[0].device_kind, "platform": jax.devices()[0].platform,
        "jax": jax.__version__, "mujoco": mujoco.__version__, "mujoco_mjx": version("mujoco-mjx"),
    }
    if "heterogeneous" in modes:
        out["heterogeneous"] = _rates([_run(buckets, sizes, impl, steps, warmup)])
        peak = _peak_memory()
        out["peak_device_bytes_per_env"] = None if peak is None else peak / sum(sizes)
    if "homogeneous" in modes:
        out["homogeneous"] = _rates([_run([b], [n], impl, steps, warmup) for b, n in zip(buckets, sizes)])
    if "cpu" in modes:
        from .mujoco.bench import measure_cpu

        cpu = measure_cpu(plans, int(cfg.get("cpu_envs", 8)), int(cfg.get("cpu_steps", 10)), resets=1)
        substeps = float(np.mean([p.n_substeps for p in plans]))
        out["cpu"] = {"env_steps_per_s": cpu["interactions_per_s"] * substeps,
                      **{k: cpu[k] for k in ("interactions_per_s", "interactions_per_cpu_s", "num_envs", "threads",
                                             "reset_ms_mean", "reset_ms_max", "load_average_1min")}}
    ratios = {}
    for a, b in (("heterogeneous", "homogeneous"), ("heterogeneous", "cpu"), ("homogeneous", "cpu")):
        if a in out and b in out:
            ratios[f"{a}_over_{b}"] = out[a]["env_steps_per_s"] / out[b]["env_steps_per_s"]
    out["ratios"] = ratios
    return out
