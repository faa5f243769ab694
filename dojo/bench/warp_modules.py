"""`dojo bench kernels`: which MuJoCo Warp modules a cold start of a task mix compiles, found on any machine.

Why. On an empty Warp kernel cache an engine compiles every module its buckets' steps launch, one after another:
the 24 simulation tasks' 29 buckets compiled 97 modules in 140-191 s on H100 machines (2026-11-28), and neither
worker processes nor threads made that shorter (README, speed). What is left is to need fewer modules: MuJoCo Warp
generates kernels per model (its DoF count's solver kernels, its collision pairs, its constraint row count), so the
number of distinct modules is a property of the buckets' models, and that can be counted without a GPU.

How. One MuJoCo Warp step of one world of each bucket's model runs on Warp's CPU device with the launches recorded
instead of executed: `wp.launch` and `wp.launch_tiled` note the module of a kernel launched over a non-empty grid
(Warp loads no module for an empty launch), and `wp.capture_while` / `wp.capture_if` run their bodies once. Nothing
is compiled and nothing is simulated: seconds for the whole mix. Checked against the GPU on the 24 simulation tasks
(H100, 2026-11-28): 95 of the 96 kernel names recorded here are the modules that machine compiled for the same
buckets (the one apart is a sparse-solver kernel whose block size comes from the device).

Counts only: a module's compile time varies from under a second to about 19 s (a convex-convex collision kernel).
Needs warp-lang (any machine; MuJoCo Warp ships inside mujoco-mjx).
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from contextlib import ExitStack
from typing import Any, Callable, Sequence
from unittest import mock

import numpy as np

from dojo.backends.mjx.batch import contact_capacity
from dojo.backends.mjx.bucket import Bucket

log = logging.getLogger(__name__)
NAMED_KERNEL = "__locals__"
"""Generated kernels live in modules of their own, named after the kernel and its hash (`<factory>__locals__
kernel_<hash>`): that name identifies the kernel on every device; a module of shared kernels is named after its
Python module, so its content hash is added."""


def _module_name(module: Any) -> str:
    if NAMED_KERNEL in module.name:
        return str(module.name)
    return f"{module.name}_{module.get_module_hash().hex()[:7]}"


def _empty(dim: Any) -> bool:
    if dim is None:
        return False
    return int(np.prod(dim if isinstance(dim, (tuple, list)) else [dim])) == 0


def _recording(wp: Any, seen: set[str]) -> ExitStack:
    """Warp's launch and conditional-capture functions replaced by recorders until the stack closes."""

    def launch(kernel: Any, *args: Any, **kwargs: Any) -> None:
        if not _empty(kwargs.get("dim", args[0] if args else None)):
            seen.add(_module_name(kernel.module))

    def capture_while(condition: Any, while_body: Callable[..., None], **kwargs: Any) -> None:
        while_body(**kwargs)

    def capture_if(condition: Any, on_true: Callable[..., None] | None = None,
                   on_false: Callable[..., None] | None = None, **kwargs: Any) -> None:
        for branch in (on_true, on_false):
            if callable(branch):
                branch(**kwargs)

    stack = ExitStack()
    for name, stand_in in (("launch", launch), ("launch_tiled", launch), ("capture_while", capture_while),
                           ("capture_if", capture_if)):
        stack.enter_context(mock.patch.object(wp, name, stand_in))
    return stack


def bucket_modules(bucket: Bucket) -> set[str]:
    """The Warp modules one step of `bucket`'s model launches, with the engine's contact and row capacities."""
    import warp as wp
    from mujoco.mjx.third_party import mujoco_warp as mjw

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    wp.init()
    seen: set[str] = set()
    contacts, rows = contact_capacity(bucket)
    with wp.ScopedDevice("cpu"):
        model = mjw.put_model(bucket.model)
        data = mjw.make_data(bucket.model, nworld=1, naconmax=contacts, njmax=rows)
        with _recording(wp, seen):
            mjw.step(model, data)
    return seen


def kernel_figures(buckets: Sequence[Bucket]) -> dict[str, Any]:
    """The modules of every bucket: how many in all, how many every bucket shares, how many of each generated
    kernel, and per bucket its DoFs, rows and the modules no other bucket needs."""
    start = time.perf_counter()
    sets = {b.key: bucket_modules(b) for b in buckets}
    union = set().union(*sets.values())
    shared = set.intersection(*sets.values()) if sets else set()
    uses = Counter(m for s in sets.values() for m in s)
    per_bucket = {b.key: {"tasks": list(b.tasks), "nv": int(b.model.nv), "rows": contact_capacity(b)[1],
                          "modules": len(sets[b.key]), "own": sorted(m for m in sets[b.key] if uses[m] == 1)}
                  for b in buckets}
    kinds = Counter(m.split(NAMED_KERNEL)[0] for m in union if NAMED_KERNEL in m)
    return {"modules": len(union), "shared_by_every_bucket": len(shared),
            "generated_kernels": dict(kinds.most_common()), "per_bucket": per_bucket,
            "seconds": time.perf_counter() - start}


def bench_kernels(cfg: dict[str, Any]) -> dict[str, Any]:
    """`dojo bench kernels`: the plans of `dojo bench sim` (`tasks`, `episodes`, `plans`), bucketed as the mjx
    backend would (`backend.merge`, `backend.merge_growth`; `dof_quantum`: their DoFs rounded up, `dof_rounding`),
    and the Warp modules their steps need."""
    from importlib.metadata import version

    from dojo.backends.mjx import merge_growth
    from dojo.backends.mjx.bucket import make_buckets
    from dojo.backends.mjx.dof_rounding import round_bucket
    from dojo.bench.sim_bench import load_plans

    try:
        import warp  # noqa: F401
    except ImportError:
        raise RuntimeError("dojo bench kernels needs warp-lang (pip install 'warp-lang>=1.19'); MuJoCo Warp itself "
                           "ships inside mujoco-mjx") from None
    backend = cfg.get("backend") or {}
    plans = load_plans(cfg)
    merge = bool(backend.get("merge", False))
    quantum = int(cfg.get("dof_quantum") or 1)
    buckets = [round_bucket(b, quantum)
               for b in make_buckets(plans, merge=merge, growth=merge_growth(backend.get("merge_growth")))]
    log.info("%d plans in %d buckets", len(plans), len(buckets))
    return {"what": "kernels", "tasks": sorted({p.task for p in plans}), "episodes": len(plans), "merge": merge,
            "dof_quantum": quantum,
            "buckets": len(buckets), "warp": version("warp-lang"), "mujoco_mjx": version("mujoco-mjx"),
            **kernel_figures(buckets)}
