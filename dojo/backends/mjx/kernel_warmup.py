"""MuJoCo Warp's kernels for every bucket compiled side by side, on threads of this process, before an engine runs.

Why. MuJoCo Warp generates kernels per model (its collision pairs, its DoF count's Cholesky, its constraint types)
and Warp compiles a module the first time a launch needs it, in the launching thread: an engine's first step
compiles bucket after bucket on one CPU core. On an empty kernel cache the 24 simulation tasks (29 buckets, 97
modules) spent 140 s so on one H100 machine and 209 s on an H200 machine (2026-11-28), while 15 cores idled.

How. Warp 1.19 compiles on several threads of one process by design: its Python code generation is serialised
under one lock and the NVRTC compile, the long part, runs outside it (`warp._src.context.Module._compile`). So each
bucket's model is stepped once, one world, on a thread of its own, and whatever that step launches is compiled
there and then, into Warp's on-disk kernel cache and into this process's loaded modules, which the engine's own
first step then finds. The first bucket goes alone first: most modules (smoothing, the solver, the broadphase)
are shared by every bucket, and compiled once that way instead of once per thread. Capacities are the engine's
(`contact_capacity`): a dense constraint kernel is generated for its row count.

Worker processes were tried first (2026-11-28) and were slower than compiling serially: 180 s against 140 s on
the H100, each process compiling the shared modules again and building its own precompiled header.
"""

from __future__ import annotations

import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

from dojo.backends.mjx.batch import contact_capacity
from dojo.backends.mjx.bucket import Bucket

log = logging.getLogger(__name__)


def thread_count(requested: int | str | None, buckets: int) -> int:
    """`backend.kernel_threads` as a count of threads: `auto` (or null) is one per CPU core; never more than the
    buckets after the first, which compiles alone. 0 when there is nothing to overlap (0 or 1 asked for, or one
    bucket): the engine then compiles its kernels itself, as MuJoCo Warp does on its own."""
    if requested in (None, "", "auto"):
        count = os.cpu_count() or 1
    else:
        try:
            count = int(requested)
        except (TypeError, ValueError):
            raise ValueError(f"backend.kernel_threads must be a count or 'auto', got {requested!r}") from None
        if count < 0:
            raise ValueError(f"backend.kernel_threads must be at least 0, got {count}")
    count = min(count, buckets - 1)
    return count if count > 1 else 0


@dataclass
class Warmup:
    """What a warm-up did, for `dojo bench`'s JSON and the run's log."""

    buckets: int
    threads: int
    seconds: float
    first_s: float = 0.0
    """The first bucket, alone: the modules every bucket shares."""
    failed: dict[str, str] = field(default_factory=dict)

    def figures(self) -> dict[str, Any]:
        return {"buckets": self.buckets, "threads": self.threads, "seconds": self.seconds, "first_s": self.first_s,
                "failed": dict(self.failed)}


def step_once(bucket: Bucket) -> None:
    """One MuJoCo Warp step of one world of `bucket`'s model, which compiles (or loads) every kernel it launches;
    waited for, so that its buffers are freed now and not while an engine captures a CUDA graph (`capture`)."""
    import warp as wp
    from mujoco.mjx.third_party import mujoco_warp as mjw

    wp.init()
    contacts, rows = contact_capacity(bucket)
    model = mjw.put_model(bucket.model)
    data = mjw.make_data(bucket.model, nworld=1, naconmax=contacts, njmax=rows)
    mjw.step(model, data)
    wp.synchronize_device()


def warm_kernels(buckets: Sequence[Bucket], threads: int | str | None = "auto",
                 step: Callable[[Bucket], None] = step_once) -> Warmup:
    """Compile the buckets' Warp kernels on `thread_count(threads)` threads: the first bucket alone, then the
    others side by side. A bucket whose step fails costs only its head start (the engine compiles what is missing
    itself, and raises if its own step fails); the failure is logged and reported. `step` is for tests."""
    count = thread_count(threads, len(buckets))
    if not count:
        return Warmup(len(buckets), 0, 0.0)
    failed: dict[str, str] = {}

    def attempt(bucket: Bucket) -> None:
        try:
            step(bucket)
        except Exception as error:  # noqa: BLE001 - the engine compiles what a failed warm-up left out
            failed[bucket.key] = f"{type(error).__name__}: {error}"

    start = time.perf_counter()
    attempt(buckets[0])
    first = time.perf_counter() - start
    with ThreadPoolExecutor(count, thread_name_prefix="warp-kernels") as pool:
        list(pool.map(attempt, buckets[1:]))
    warm = Warmup(len(buckets), count, time.perf_counter() - start, first, failed)
    log.info("MuJoCo Warp kernels of %d bucket(s) compiled or loaded in %.1f s (%.1f s the first, then %d "
             "threads)%s", warm.buckets, warm.seconds, first, count, f"; {len(failed)} failed: {failed}" if failed
             else "")
    return warm
