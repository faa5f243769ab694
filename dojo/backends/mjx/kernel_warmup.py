"""MuJoCo Warp's kernels for every bucket compiled side by side, in worker processes, before the engine needs them.

Why. MuJoCo Warp generates kernels per model (its collision pairs, constraint types, solver and sizes) and Warp
compiles each the first time a launch needs it, in the launching thread, one after another: on an empty kernel
cache the 12-task mix spent about 240 of its 307 s set-up compiling (one H100, 2026-11-25), 20-53 s per collision
kernel, on one CPU core while the machine's others idled.

How. Each worker process builds one bucket's model with MuJoCo Warp (the copy MJX vendors, so the kernels are the
ones MJX launches: MJX builds its Warp model with the same `put_model`) and steps one world once, which compiles
every kernel a step of that structure launches and writes it to Warp's on-disk kernel cache; the engine's own
first step then loads them from there. Warp builds each module in a folder of its own process and moves it into
place atomically, so concurrent writers are safe. Kernels every bucket shares are compiled by several workers at
once: CPU time spent for wall time. Contact and constraint capacities are the engine's (`contact_capacity`):
a dense constraint kernel is generated for its row count.

A worker that fails (no GPU memory left, say) costs nothing but its head start: the engine compiles what is missing
itself, as it would without the warm-up, and the failure is logged.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import mujoco

from dojo.backends.mjx.batch import contact_capacity
from dojo.backends.mjx.bucket import Bucket

log = logging.getLogger(__name__)


def worker_count(requested: int | str | None, buckets: int) -> int:
    """`backend.kernel_workers` as a process count: `auto` (or null) is one per CPU core, at most one per bucket;
    0 or 1 means no warm-up (the engine compiles serially, as MuJoCo Warp does on its own), and so does one
    bucket: a single worker would compile what the engine compiles, no sooner."""
    if requested in (None, "", "auto"):
        count = os.cpu_count() or 1
    else:
        try:
            count = int(requested)
        except (TypeError, ValueError):
            raise ValueError(f"backend.kernel_workers must be a count or 'auto', got {requested!r}") from None
        if count < 0:
            raise ValueError(f"backend.kernel_workers must be at least 0, got {count}")
    count = min(count, buckets)
    return count if count > 1 else 0


@dataclass
class Job:
    """What a worker needs to compile one bucket's kernels: its model and the engine's buffer sizes per world."""

    key: str
    model: mujoco.MjModel
    contacts: int
    rows: int


@dataclass
class Warmup:
    """What a warm-up did: for `dojo bench`'s JSON and the run's log."""

    buckets: int
    workers: int
    seconds: float
    failed: dict[str, str] = field(default_factory=dict)

    def figures(self) -> dict[str, Any]:
        return {"buckets": self.buckets, "workers": self.workers, "seconds": self.seconds,
                "failed": dict(self.failed)}


def _output_to_stderr() -> None:
    """A worker's initializer: whatever it prints (Warp's banner, a driver's warning) goes to standard error, so
    that `dojo bench` keeps standard output to its one JSON line."""
    os.dup2(2, 1)


def compile_step(job: Job) -> float:
    """In a worker process: compile (or find cached) every kernel one MuJoCo Warp step of `job.model` launches.
    Returns the seconds it took."""
    import jax
    import warp as wp
    from mujoco.mjx.third_party import mujoco_warp as mjw

    jax.config.update("jax_platforms", "cpu")  # MJX (imported with its MuJoCo Warp) must not take GPU memory here
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    start = time.perf_counter()
    wp.init()
    model = mjw.put_model(job.model)
    data = mjw.make_data(job.model, nworld=1, naconmax=job.contacts, njmax=job.rows)
    mjw.step(model, data)
    wp.synchronize_device()
    return time.perf_counter() - start


def jobs_for(buckets: Sequence[Bucket]) -> list[Job]:
    """One job per bucket, with the capacities the engine will allocate per world."""
    return [Job(b.key, b.model, *contact_capacity(b)) for b in buckets]


def warm_kernels(buckets: Sequence[Bucket], workers: int | str | None = "auto",
                 compile_one: Callable[[Job], float] = compile_step) -> Warmup:
    """Compile the buckets' Warp kernels into the kernel cache in `worker_count(workers)` processes at once.

    Workers are started fresh (`spawn`): a process that has started CUDA or JAX cannot be forked safely. They
    find Warp's kernel cache where this process does (`WARP_CACHE_PATH`, else Warp's default; dojo never sets
    `warp.config.kernel_cache_dir`). `compile_one` runs in the workers; anything but `compile_step` is for tests.
    """
    count = worker_count(workers, len(buckets))
    if not count:
        return Warmup(len(buckets), 0, 0.0)
    start = time.perf_counter()
    failed: dict[str, str] = {}
    with ProcessPoolExecutor(count, mp_context=multiprocessing.get_context("spawn"),
                             initializer=_output_to_stderr) as pool:
        futures = {job.key: pool.submit(compile_one, job) for job in jobs_for(buckets)}
        for key, future in futures.items():
            try:
                log.debug("kernels of %s: %.1f s", key, future.result())
            except Exception as error:  # the engine compiles what a failed worker left out
                failed[key] = f"{type(error).__name__}: {error}"
    warm = Warmup(len(buckets), count, time.perf_counter() - start, failed)
    log.info("MuJoCo Warp kernels of %d bucket(s) compiled or found cached in %.1f s by %d worker processes%s",
             warm.buckets, warm.seconds, count, f" ({len(failed)} failed: {failed})" if failed else "")
    return warm
