"""Where a lane's GPU time goes, kernel by kernel (`StreamEngine.kernel_ms`, `dojo bench sim kernel_times=N`).

Why: `lane_ms` says how long each lane's tick takes alone, and one lane can be far slower than its size suggests
(H200, 2026-12-02, 1,200 environments: the bucket of `press_by_number` and `put_bottles_into_dustbin`, 100
environments at 67 DoFs, took 47.8 ms a tick against 31.5 ms for 350 environments of seven other tasks at 131).
Which of MuJoCo Warp's kernels take that time (collision, the solver, ...) is the next question, and the answer
decides what to change. Warp times kernel launches with CUDA events (`wp.timing_begin`), outside graph capture
only, so the lane's tick is run once more launch by launch: the times are each kernel's own on an otherwise idle
GPU, and their sum is kernel time alone (no gaps between launches, no host waits), to set beside `lane_ms`.
"""

from __future__ import annotations

from typing import Any, Iterable


def kernel_table(results: Iterable[Any], top: int) -> dict[str, Any]:
    """One tick's Warp timing results (objects with `name` and `elapsed` ms) summed by kernel name: the total GPU
    milliseconds and launches, and the `top` kernels by time, each with its milliseconds and launches (ties by
    name, so the table is stable)."""
    by_name: dict[str, list[float]] = {}
    for result in results:
        by_name.setdefault(result.name, []).append(float(result.elapsed))
    rows = sorted(((name, sum(times), len(times)) for name, times in by_name.items()), key=lambda r: (-r[1], r[0]))
    return {"gpu_ms": sum(ms for _, ms, _ in rows), "launches": sum(n for _, _, n in rows),
            "kernels": [{"name": name, "ms": ms, "launches": n} for name, ms, n in rows[:max(top, 0)]]}
