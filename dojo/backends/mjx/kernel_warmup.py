"""MuJoCo Warp's kernels for every bucket compiled ahead of time, side by side on threads, before an engine loads
them. Off by default (`backend.kernel_threads=0`): an experiment until a GPU measures it.

Why. An engine's first step compiles every Warp module its buckets launch, one after another: the 24 simulation
tasks' 29 buckets compiled 97 modules in 140-191 s on H100 machines (2026-11-28). Loading modules on threads
(`wp.force_load` with workers, or the first steps of buckets on threads) was slower still on the H100, about 11x
(README, speed), and worker processes did not help either. Warp's CUDA compiler (NVRTC, inside warp.so) does
overlap on threads where no CUDA context is involved: compiling one `stack_blocks` bucket's 35 modules for sm_90 on
the 2-core CPU machine took 98 s on 2 threads against 151 s serially.

How. Every bucket's launches are recorded without running them (`warp_launches`, on the device the engine will
use, so that MuJoCo Warp picks the same block sizes), each distinct (module, block size) is compiled for that
device on a thread pool, compiled only (Warp's `Module._compile`, with the options and variant hash a launch of
that block size resolves: Warp 1.19's own steps of `Module.load`), and written to Warp's kernel cache. Nothing is
loaded into the CUDA context here: the engine's first step finds every module in the cache and loads it, serially,
as it would have anyway. A module that fails to compile costs only its head start (the engine compiles it itself,
and raises if that fails too); it is reported.
"""

from __future__ import annotations

import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

from dojo.backends.mjx.bucket import Bucket
from dojo.backends.mjx.warp_launches import Launches, recorded_launches

log = logging.getLogger(__name__)


def thread_count(requested: int | str | None) -> int:
    """`backend.kernel_threads` as a count: `auto` is one per CPU core; 0 (or null) turns the warm-up off."""
    if requested in (None, ""):
        return 0
    if requested == "auto":
        return os.cpu_count() or 1
    try:
        count = int(requested)
    except (TypeError, ValueError):
        raise ValueError(f"backend.kernel_threads must be a count, 'auto' or 0, got {requested!r}") from None
    if count < 0:
        raise ValueError(f"backend.kernel_threads must be at least 0, got {count}")
    return count


@dataclass
class Warmup:
    """What a warm-up did, for `dojo bench`'s JSON and the run's log."""

    threads: int
    modules: int = 0
    compiled: int = 0
    """Modules compiled now (the others were in the kernel cache already)."""
    record_s: float = 0.0
    seconds: float = 0.0
    failed: dict[str, str] = field(default_factory=dict)

    def figures(self) -> dict[str, Any]:
        return {"threads": self.threads, "modules": self.modules, "compiled": self.compiled,
                "record_s": self.record_s, "seconds": self.seconds, "failed": dict(self.failed)}


def compile_variant(module: Any, block_dim: Any, device: Any) -> bool:
    """Compile `module`'s variant for a launch of `block_dim` on `device` into Warp's kernel cache without loading
    it; False when the cache had it. Follows Warp 1.19's `Module.load` (its private steps: the launch's block size
    resolved as `wp.launch` does, the variant's hash, its resolved options, `_compile`)."""
    from warp._src.context import _resolve_launch_block_dim

    block = _resolve_launch_block_dim(device, block_dim)
    module.get_module_hash(block)
    return bool(module._compile(device, options=module.resolved_options[block]))


def warm_kernels(buckets: Sequence[Bucket], threads: int | str | None) -> Warmup:
    """Record every bucket's launches on Warp's current device, then compile the distinct variants on
    `thread_count(threads)` threads (`compile_all`); nothing when that is 0."""
    count = thread_count(threads)
    if not count:
        return Warmup(0)
    import warp as wp

    wp.init()
    device = wp.get_device()
    start = time.perf_counter()
    launches: Launches = {}
    for bucket in buckets:
        launches.update(recorded_launches(bucket, device))
    warm = compile_all(launches, count, device)
    warm.record_s = time.perf_counter() - start - warm.seconds
    log.info("MuJoCo Warp: %d kernel module(s) of %d bucket(s) ready in %.1f s (%d compiled on %d threads, "
             "recorded in %.1f s)%s", warm.modules, len(buckets), warm.seconds, warm.compiled, count, warm.record_s,
             f"; {len(warm.failed)} failed: {warm.failed}" if warm.failed else "")
    return warm


def compile_all(launches: Launches, threads: int, device: Any,
                compile_one: Callable[[Any, Any, Any], bool] = compile_variant) -> Warmup:
    """Compile every recorded (module, block size) for `device` on `threads` threads; a failure is reported, not
    raised. `compile_one` is for tests."""
    failed: dict[str, str] = {}

    def attempt(item: tuple[Any, Any]) -> bool:
        module, block = item
        try:
            return compile_one(module, block, device)
        except Exception as error:  # noqa: BLE001 - the engine compiles what a failed warm-up left out
            failed[f"{module.name}@{block}"] = f"{type(error).__name__}: {error}"
            return False

    start = time.perf_counter()
    with ThreadPoolExecutor(threads, thread_name_prefix="warp-compile") as pool:
        compiled = sum(pool.map(attempt, launches.values()))
    return Warmup(threads, len(launches), compiled, 0.0, time.perf_counter() - start, failed)
