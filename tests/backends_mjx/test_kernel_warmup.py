"""The Warp kernel warm-up's orchestration, on any machine: how many worker processes a setting means, and that
every bucket's model and buffer sizes reach a worker process of its own, a failing worker is reported and the
others still run. The compilation itself needs an NVIDIA GPU (`test_warp_gpu.py`); here a stand-in worker
records what it was given."""

from __future__ import annotations

import json
import os

import pytest
from conftest import toy_plan
from warmup_standin import record_job

from dojo.backends.mjx.batch import contact_capacity
from dojo.backends.mjx.bucket import make_buckets
from dojo.backends.mjx.kernel_warmup import warm_kernels, worker_count


@pytest.fixture(scope="module")
def buckets():
    plans = [toy_plan(task="a"), toy_plan(task="b", items=("ball",)), toy_plan(task="c", items=("box", "ball"))]
    found = make_buckets(plans)
    assert len(found) == 3
    return found


def test_worker_counts():
    cores = os.cpu_count() or 1
    assert worker_count("auto", 50) == (min(cores, 50) if cores > 1 else 0)
    assert worker_count(None, 1) == 0  # one bucket: its engine compiles it as fast
    assert worker_count(0, 9) == 0 and worker_count(1, 9) == 0
    assert worker_count(4, 9) == 4 and worker_count("4", 2) == 2
    for bad in ("many", -1, 2.5j):
        with pytest.raises(ValueError, match="kernel_workers"):
            worker_count(bad, 3)


def test_each_bucket_reaches_a_worker_process_with_its_model_and_capacities(buckets, tmp_path, monkeypatch):
    monkeypatch.setenv("WARMUP_RECORDS", str(tmp_path))
    warm = warm_kernels(buckets, 2, compile_one=record_job)
    assert warm.figures()["buckets"] == 3 and warm.workers == 2 and not warm.failed
    records = [json.loads(p.read_text()) for p in tmp_path.iterdir()]
    assert sorted(r["key"] for r in records) == sorted(b.key for b in buckets)
    assert all(r["pid"] != os.getpid() for r in records)
    for bucket in buckets:
        (got,) = [r for r in records if r["key"] == bucket.key]
        assert (got["nbody"], got["ngeom"]) == (bucket.model.nbody, bucket.model.ngeom)
        assert (got["contacts"], got["rows"]) == contact_capacity(bucket)


def test_a_failing_worker_is_reported_and_the_others_still_compile(buckets, tmp_path, monkeypatch):
    monkeypatch.setenv("WARMUP_RECORDS", str(tmp_path))
    monkeypatch.setenv("WARMUP_FAIL", buckets[1].key)
    warm = warm_kernels(buckets, 3, compile_one=record_job)
    assert list(warm.failed) == [buckets[1].key] and "out of GPU memory" in warm.failed[buckets[1].key]
    assert sorted(json.loads(p.read_text())["key"] for p in tmp_path.iterdir()) == sorted(
        b.key for b in (buckets[0], buckets[2]))


def test_no_workers_means_no_warm_up(buckets, tmp_path, monkeypatch):
    monkeypatch.setenv("WARMUP_RECORDS", str(tmp_path))
    assert warm_kernels(buckets, 0, compile_one=record_job).workers == 0
    assert not list(tmp_path.iterdir())


def test_the_backend_refuses_a_bad_worker_setting_on_any_machine():
    from dojo.backends.mjx.backend import MjxBackend

    with pytest.raises(ValueError, match="kernel_workers"):
        MjxBackend(impl="jax", kernel_workers="lots")
