"""The kernel warm-up's orchestration on a CPU, with a stand-in for the MuJoCo Warp step: the first bucket alone,
then the others on threads side by side; failures reported, never raised; settings checked. The real step is
tested on a GPU (`test_warp_gpu.py`)."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import pytest

from dojo.backends.mjx.kernel_warmup import thread_count, warm_kernels


def _buckets(n: int) -> list[SimpleNamespace]:
    return [SimpleNamespace(key=f"b{k}") for k in range(n)]


def test_thread_count_reads_the_setting():
    assert thread_count(4, 10) == 4
    assert thread_count("3", 10) == 3
    assert thread_count(16, 5) == 4  # never more than the buckets after the first
    assert thread_count(0, 10) == 0 and thread_count(1, 10) == 0
    assert thread_count("auto", 1) == 0  # one bucket: nothing to overlap
    assert thread_count(None, 3) in (0, 2)
    for bad in ("many", -1):
        with pytest.raises(ValueError, match="kernel_threads"):
            thread_count(bad, 4)


def test_the_first_bucket_compiles_alone_then_the_others_overlap():
    events: list[tuple[str, str, float]] = []
    lock = threading.Lock()
    barrier = threading.Barrier(3, timeout=10)  # three later buckets must be in their step at the same time

    def step(bucket):
        with lock:
            events.append(("start", bucket.key, time.perf_counter()))
        if bucket.key != "b0":
            barrier.wait()
        with lock:
            events.append(("end", bucket.key, time.perf_counter()))

    warm = warm_kernels(_buckets(4), 3, step=step)
    assert warm.threads == 3 and warm.buckets == 4 and not warm.failed
    assert [e[:2] for e in events[:2]] == [("start", "b0"), ("end", "b0")]
    assert {e[1] for e in events[2:]} == {"b1", "b2", "b3"}
    assert 0 < warm.first_s <= warm.seconds


def test_a_failed_bucket_is_reported_and_the_others_still_compile():
    done = []

    def step(bucket):
        if bucket.key == "b2":
            raise RuntimeError("out of device memory")
        done.append(bucket.key)

    warm = warm_kernels(_buckets(4), 2, step=step)
    assert sorted(done) == ["b0", "b1", "b3"]
    assert warm.failed == {"b2": "RuntimeError: out of device memory"}
    assert warm.figures()["failed"] == warm.failed


def test_nothing_to_overlap_steps_nothing():
    called = []
    warm = warm_kernels(_buckets(5), 0, step=called.append)
    assert called == [] and warm.threads == 0 and warm.seconds == 0.0
