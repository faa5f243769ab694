"""`dojo bench kernels`: which MuJoCo Warp modules a cold start of a task mix compiles, found on any machine.

Why. On an empty Warp kernel cache an engine compiles every module its buckets' steps launch, one after another:
the 24 simulation tasks' 29 buckets compiled 97 modules in 140-191 s on H100 machines and 128 s on an H200
(2026-11-28), and compiling or loading them on threads or in worker processes made that longer (README, speed).
The lever left is needing fewer modules. MuJoCo Warp generates kernels per model (its DoF count's solver kernels,
its collision pairs, its constraint row count), so the number of distinct modules is a property of the buckets'
models, and that can be counted without a GPU.

How. One MuJoCo Warp step of one world of each bucket's model runs on Warp's CPU device with the launches recorded
instead of executed (`warp_launches`): nothing is compiled and nothing is simulated, seconds for the whole mix.
Checked against the GPU on the 24 simulation tasks (H100, 2026-11-28): 95 of the 96 kernel names recorded here are
the modules that machine compiled for the same buckets (the one apart is a sparse-solver kernel whose block size
comes from the device).

Counts only: a module's compile time varies from under a second to about 19 s (a convex-convex collision kernel).
Per bucket it also counts the kernels a lane's tick launches (`recorded_tick`), the other figure a change to the
tick moves: at small batches the launches, not their arithmetic, set a lane's pace on the GPU.
Needs warp-lang (any machine; MuJoCo Warp ships inside mujoco-mjx).
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from pathlib import Path
from typing import Any, Mapping, Sequence

from dojo.backends.mjx.batch import contact_capacity
from dojo.backends.mjx.bucket import Bucket
from dojo.backends.mjx.warp_launches import Launches, recorded_tick

log = logging.getLogger(__name__)
NAMED_KERNEL = "__locals__"
"""Generated kernels live in modules of their own, named after the kernel and its hash (`<factory>__locals__
kernel_<hash>`): that name identifies the kernel on every device; a module of shared kernels is named after its
Python module, so its content hash is added."""


def _module_name(module: Any) -> str:
    if NAMED_KERNEL in module.name:
        return str(module.name)
    return f"{module.name}_{module.get_module_hash().hex()[:7]}"


def bucket_modules(bucket: Bucket) -> set[str]:
    """The Warp modules a step, a forward and a lane's refresh of `bucket`'s model launch (`warp_launches`, on
    Warp's CPU device: any machine), by name; a module launched with several block sizes counts once."""
    return _module_names(recorded_tick(bucket, "cpu")[0])


def _module_names(launches: Launches) -> set[str]:
    return {_module_name(module) for module in launches.values()}


def kernel_figures(buckets: Sequence[Bucket], arch: int | None = None, jobs: int = 1,
                   sizes: Sequence[int] | None = None) -> dict[str, Any]:
    """The modules of every bucket: how many in all, how many every bucket shares, how many of each generated
    kernel, and per bucket its DoFs, rows, the modules no other bucket needs and the kernels its lane launches
    (`recorded_tick`: a step, a forward, the lane's refresh, a tick), from one recording each, of a lane of
    `sizes[k]` worlds (one each when None). With `arch`, every module is also compiled for `sm_<arch>` into Warp's
    kernel cache, `jobs` at a time (`kernel_cache`), under `ahead`."""
    start = time.perf_counter()
    sizes = list(sizes) if sizes is not None else [1] * len(buckets)
    recorded = {b.key: recorded_tick(b, "cpu", size) for b, size in zip(buckets, sizes)}
    sets = {key: _module_names(launches) for key, (launches, _) in recorded.items()}
    union = set().union(*sets.values())
    shared = set.intersection(*sets.values()) if sets else set()
    uses = Counter(m for s in sets.values() for m in s)
    per_bucket = {b.key: {"tasks": list(b.tasks), "worlds": size, "nv": int(b.model.nv),
                          "rows": contact_capacity(b)[1],
                          "modules": len(sets[b.key]), "own": sorted(m for m in sets[b.key] if uses[m] == 1),
                          "launches": recorded[b.key][1]}
                  for b, size in zip(buckets, sizes)}
    kinds = Counter(m.split(NAMED_KERNEL)[0] for m in union if NAMED_KERNEL in m)
    figures = {"modules": len(union), "shared_by_every_bucket": len(shared),
               "generated_kernels": dict(kinds.most_common()), "per_bucket": per_bucket,
               "seconds": time.perf_counter() - start}
    if arch is not None:
        from dojo.backends.mjx.kernel_cache import compile_ahead

        every = {key: module for launches, _ in recorded.values() for key, module in launches.items()}
        figures["ahead"] = compile_ahead(every, int(arch), jobs)
    return figures


def bench_kernels(cfg: dict[str, Any]) -> dict[str, Any]:
    """`dojo bench kernels`: the plans of `dojo bench sim` (`tasks`, `episodes`, `plans`) that `dojo run
    backend=mjx` would give the mjx backend (`mjx_plans`), bucketed as it would (`backend.merge`,
    `backend.merge_growth`; under `merge=auto` as a run of `num_envs` environments on a GPU decides; `dof_quantum`:
    their DoFs rounded up, `dof_rounding`), and the Warp modules their steps need in lanes of the sizes such a run
    gives them on one GPU (`num_envs`: a bucket's lane holds as many worlds as its plans the run's slots can hold
    at once); with `arch`, those modules compiled for that GPU architecture into Warp's kernel cache (`jobs` at a
    time), on this machine, GPU or not."""
    from importlib.metadata import version

    from dojo.backends.mjx.bucket_cache import cached_buckets
    from dojo.backends.mjx.dof_rounding import round_bucket
    from dojo.backends.mjx import merge_settings
    from dojo.backends.mjx.merge_groups import choose_merge, task_groups
    from dojo.backends.mjx.slots import bucket_rows
    from dojo.bench.sim_bench import load_plans

    try:
        import warp  # noqa: F401
    except ImportError:
        raise RuntimeError("dojo bench kernels needs warp-lang (pip install 'warp-lang>=1.19'); MuJoCo Warp itself "
                           "ships inside mujoco-mjx") from None
    backend = cfg.get("backend") or {}
    plans, elsewhere = mjx_plans(load_plans(cfg), backend)
    compiler = plans_compiler(cfg.get("plans"))
    # as `dojo run` on a GPU without cameras (physics on streams) with `num_envs` environments would bucket them
    slots = min(int(cfg.get("num_envs") or len(plans)), len(plans))
    merge, growth, _ = choose_merge(*merge_settings(backend), True, slots, task_groups(plans))
    quantum = int(cfg.get("dof_quantum") or 1)
    buckets = [round_bucket(b, quantum) for b in cached_buckets(plans, merge, growth)[0]]
    # and size their lanes as its backend does on one GPU (`MjxBackend.load`)
    sizes = [bucket_rows(slots, len(b.members)) for b in buckets]
    log.info("%d plans in %d buckets", len(plans), len(buckets))
    return {"what": "kernels", "tasks": sorted({p.task for p in plans}), "episodes": len(plans),
            "run_on_mujoco": elsewhere, "merge": merge, "growth": growth if math.isfinite(growth) else "inf",
            "dof_quantum": quantum, "plans_compiler": compiler,
            "buckets": len(buckets), "warp": version("warp-lang"), "mujoco_mjx": version("mujoco-mjx"),
            **kernel_figures(buckets, cfg.get("arch"), int(cfg.get("jobs") or 1), sizes)}


def plans_compiler(folder: str | None) -> str | None:
    """The compiler the plans are named by: the folder's index's (`dojo compile`'s output; None for a folder of plan
    files without one), or this install's for plans the bench compiled itself. Where the folder's is not this
    install's, say so: a GPU run reuses the folder's plans, and so finds the kernels compiled here for their
    buckets, only where its install is the plans' compiler; one like this install would compile them again under
    other names, which may bucket otherwise (a GPU with MuJoCo 4.0.0 made 46 buckets of the protocol's plans
    compiled with 4.0.1, and compiled 24 modules the cache lacked, 2026-12-03)."""
    from dojo.compiler.plan import compiler_id
    from dojo.compiler.suite_compile import index_compiler

    here = compiler_id()
    if not folder:
        return here
    found = index_compiler(Path(folder))
    if found is not None and found != here:
        log.warning("plans=%s were compiled by '%s', this install is '%s': the kernels compiled here serve a GPU "
                    "run whose install is the plans' (with this warp-lang and mujoco-mjx); one like this install "
                    "would compile the plans again and may bucket them otherwise", folder, found, here)
    return found


def mjx_plans(plans: Sequence[Any], settings: Mapping[str, Any]) -> tuple[list[Any], dict[str, int]]:
    """(the plans the mjx backend runs, {task: plans} of those `dojo run backend=mjx` sends to its fallback for a
    feature mjx lacks, `dojo.evaluation.routing`). Why: with `backend.merge` the buckets, so their modules, depend
    on which tasks share them, and kernels compiled for plans the run never gives mjx can miss the run's own
    buckets; without merge they are modules compiled for nothing."""
    from dojo.backends.registry import unsupported_features

    kept, elsewhere, verdicts = [], Counter[str](), {}
    for plan in plans:
        needs = tuple(plan.requires)
        if needs not in verdicts:
            verdicts[needs] = bool(unsupported_features("mjx", needs, settings)) if needs else False
        if verdicts[needs]:
            elsewhere[plan.task] += 1
        else:
            kept.append(plan)
    if not kept:
        raise ValueError(f"no plan here runs on backend mjx: {dict(elsewhere)} would run on its fallback")
    return kept, dict(sorted(elsewhere.items()))
