"""`bench_sim` smoke test: the output's shape and consistency, never a time.

Uses the two standard toy plans of the parity test (one bucket of two environments), so that with the
persistent compilation cache both bench modes reuse that test's compiled program.
"""

from __future__ import annotations

import json

import pytest
from conftest import CACHE_DIR, toy_plan

from dojo.backends.sim_bench import bench_sim, split_batch
from dojo.backends.mjx.bucket import make_buckets


def test_bench_sim_prints_one_json_object_with_both_modes(tmp_path):
    for s in range(2):
        toy_plan(seed=s).save(tmp_path / f"toy-{s}.json")
    cfg = {"what": "sim", "plans": str(tmp_path), "num_envs": 2, "steps": 2, "warmup": 1,
           "backend": {"name": "mjx", "impl": "auto"}, "modes": ["heterogeneous", "homogeneous"],
           "cache_dir": CACHE_DIR}
    out = json.loads(json.dumps(bench_sim(cfg)))
    assert out["impl"] == "jax" and out["num_envs"] == 2 and out["tasks"] == ["toy"]
    for mode in ("heterogeneous", "homogeneous"):
        assert out[mode]["env_steps_per_s"] > 0
        assert out[mode]["env_steps_per_s"] == pytest.approx(10 * out[mode]["interactions_per_s"])
        assert out[mode]["compilations"] == 1
    assert out["ratios"]["heterogeneous_over_homogeneous"] == pytest.approx(
        out["heterogeneous"]["env_steps_per_s"] / out["homogeneous"]["env_steps_per_s"])
    assert {"device", "jax", "mujoco", "mujoco_mjx", "peak_device_bytes_per_env"} <= set(out)


def test_split_batch_is_proportional_and_complete():
    plans = [toy_plan(seed=s) for s in range(3)] + [toy_plan(task="other", block_size=0.05)]
    buckets = make_buckets(plans)
    assert split_batch(buckets, 8) == [2, 6]
    assert sum(split_batch(buckets, 1001)) == 1001
    with pytest.raises(ValueError):
        split_batch(buckets, 1)


def test_dojo_bench_sim_cpu_mode_prints_exactly_one_json_line(tmp_path):
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-m", "dojo.runtime.cli", "bench", "sim", "modes=[cpu]",
                             "tasks=[stack_blocks]", "episodes=1", "cpu_envs=2", "cpu_steps=3"],
                            cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 1, result.stdout
    out = json.loads(lines[0])
    assert out["tasks"] == ["stack_blocks"] and set(out) >= {"cpu", "device", "mujoco", "jax"}
    cpu = out["cpu"]
    assert cpu["num_envs"] == 2 and cpu["interactions_per_s"] > 0 and cpu["interactions_per_cpu_s"] > 0
    assert cpu["env_steps_per_s"] == pytest.approx(20 * cpu["interactions_per_s"])
    assert 0 < cpu["reset_ms_mean"] <= cpu["reset_ms_max"]
