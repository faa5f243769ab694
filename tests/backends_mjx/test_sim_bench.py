"""`bench_sim` smoke test: the output's shape and consistency, never a time.

Uses the two standard toy plans of the parity test (one bucket of two environments), so that with the
persistent compilation cache both bench modes reuse that test's compiled program.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from conftest import CACHE_DIR, toy_plan

from dojo.bench.sim_bench import bench_ratios, bench_sim, ideal_mix, split_batch
from dojo.backends.mjx.bucket import make_buckets
from dojo.backends.mjx.merge_groups import GROWTH


def test_bench_sim_prints_one_json_object_with_both_modes(tmp_path):
    for s in range(2):
        toy_plan(seed=s).save(tmp_path / f"toy-{s}.json")
    cfg = {"what": "sim", "plans": str(tmp_path), "num_envs": 2, "steps": 2, "warmup": 1,
           "backend": {"name": "mjx", "impl": "auto"}, "modes": ["heterogeneous", "homogeneous", "alone"],
           "cache_dir": CACHE_DIR}
    out = json.loads(json.dumps(bench_sim(cfg)))
    assert out["impl"] == "jax" and out["num_envs"] == 2 and out["tasks"] == ["toy"]
    for mode in ("heterogeneous", "homogeneous"):
        assert out[mode]["physics_steps_per_s"] > 0
        assert out[mode]["physics_steps_per_s"] == pytest.approx(10 * out[mode]["interactions_per_s"])
        assert out[mode]["compilations"] == 1
    assert out["ratios"]["heterogeneous_over_homogeneous"] == pytest.approx(
        out["heterogeneous"]["interactions_per_s"] / out["homogeneous"]["interactions_per_s"])
    # `alone` (one task here: the same bucket and batch on the jitted engine once more), and the mix against it
    alone = out["alone"]
    assert alone["engine"] == "heterogeneous" and list(alone["per_task"]) == ["toy"]
    assert alone["per_task"]["toy"]["share"] == 1.0 and alone["per_task"]["toy"]["num_envs"] == 2
    assert alone["ideal_mix"]["interactions_per_s"] == pytest.approx(alone["per_task"]["toy"]["interactions_per_s"])
    assert out["ratios"]["heterogeneous_over_ideal_mix"] == pytest.approx(
        out["heterogeneous"]["interactions_per_s"] / alone["ideal_mix"]["interactions_per_s"])
    assert set(out["counts"]) == {"interactions", "physics_steps"}
    assert {"device", "jax", "mujoco", "mujoco_mjx", "peak_device_bytes_per_env"} <= set(out)


def test_bench_sim_merged_mode_reports_its_buckets_beside_the_separate_ones(tmp_path):
    """Two toy tasks (the plans of test_merge.py's engine test, so the compilation cache serves both): two buckets
    stepped in one tick against one merged bucket, each with its rates and one compilation."""
    for k, (task, items) in enumerate({"toy": (), "pair": ("ball", "box")}.items()):
        for s in range(2):
            toy_plan(task=task, seed=s, items=items, block_size=0.03 + 0.005 * k).save(tmp_path / f"{task}-{s}.json")
    cfg = {"what": "sim", "plans": str(tmp_path), "num_envs": 4, "steps": 2, "warmup": 1,
           "backend": {"name": "mjx", "impl": "jax"}, "modes": ["heterogeneous", "merged"], "cache_dir": CACHE_DIR}
    out = json.loads(json.dumps(bench_sim(cfg)))
    assert out["tasks"] == ["pair", "toy"] and out["buckets"] == 2 and out["bucket_sizes"] == [2, 2]
    assert out["merged"]["buckets"] == 1 and out["merged"]["bucket_sizes"] == [4]
    assert out["merged"]["growth"] == GROWTH  # the backend config's merge_growth, unset: the module's default
    assert out["merged"]["models"] == [{"tasks": ["pair", "toy"], "plans": 4, "nv": 19, "ngeom": 5, "nbody": 5}]
    for mode in ("heterogeneous", "merged"):
        assert out[mode]["interactions_per_s"] > 0 and out[mode]["compilations"] == 1
    assert out["ratios"]["merged_over_heterogeneous"] == pytest.approx(
        out["merged"]["interactions_per_s"] / out["heterogeneous"]["interactions_per_s"])
    assert "homogeneous" not in out


def test_the_ideal_mix_gives_each_task_its_share_of_the_time_at_its_own_rate():
    """Three tasks with a quarter, a quarter and half of the batch, at 10, 40 and 20 interactions/s (sub-steps 10, 10
    and 5): per interaction of the batch 0.025 + 0.00625 + 0.025 s, and 7.5 physics steps."""
    tasks = [{"share": 0.25, "interactions_per_s": 10.0, "physics_steps_per_s": 100.0},
             {"share": 0.25, "interactions_per_s": 40.0, "physics_steps_per_s": 400.0},
             {"share": 0.5, "interactions_per_s": 20.0, "physics_steps_per_s": 100.0}]
    ideal = ideal_mix(tasks)
    assert ideal["interactions_per_s"] == pytest.approx(1 / 0.05625)
    assert ideal["physics_steps_per_s"] == pytest.approx(7.5 / 0.05625)
    assert 10.0 < ideal["interactions_per_s"] < 40.0
    assert ideal_mix([{**tasks[0], "share": 1.0}])["interactions_per_s"] == pytest.approx(10.0)  # one task: itself


def test_the_stream_modes_are_also_set_against_the_separate_buckets_in_turn():
    """The protocol's figures of 2026-12-02 (H200, 1,200 envs): 222 lanes at 1,556 interactions/s concurrently and
    334 in turn on one stream, 55 merged lanes at 3,289: the merged mix is 9.8x its buckets in turn, in one run."""
    out = {"streams": {"interactions_per_s": 1556.0, "serial": {"interactions_per_s": 334.0}},
           "merged_streams": {"interactions_per_s": 3289.0, "serial": {"interactions_per_s": 719.0}}}
    ratios = bench_ratios(out)
    assert ratios["merged_streams_over_streams_serial"] == pytest.approx(3289.0 / 334.0)
    assert ratios["streams_over_streams_serial"] == pytest.approx(1556.0 / 334.0)
    assert ratios["merged_streams_over_streams"] == pytest.approx(3289.0 / 1556.0)
    assert bench_ratios({"merged_streams": out["merged_streams"]}) == {}  # no separate buckets measured: no ratio


def test_split_batch_is_proportional_and_complete():
    plans = [toy_plan(seed=s) for s in range(3)] + [toy_plan(task="other", block_size=0.05)]
    buckets = make_buckets(plans)
    assert split_batch(buckets, 8) == [2, 6]
    assert sum(split_batch(buckets, 1001)) == 1001
    with pytest.raises(ValueError):
        split_batch(buckets, 1)


def _bench(*args: str, cwd) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dojo.cli.main", "bench", "sim", "tasks=[stack_blocks]",
                           "episodes=1", *args], cwd=cwd, capture_output=True, text=True, timeout=600)


def test_dojo_bench_sim_backend_mujoco_measures_the_cpu_backend_it_names(tmp_path):
    """No GPU needed, no JAX imported (no 'tpu' message), one JSON line describing what was measured."""
    result = _bench("backend=mujoco", "num_envs=2", "steps=3", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "tpu" not in result.stderr.lower() and "ERROR" not in result.stderr
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 1, result.stdout
    out = json.loads(lines[0])
    assert out["backend"] == "mujoco" and out["num_envs"] == 2 and out["steps"] == 3
    assert out["tasks"] == ["stack_blocks"] and "jax" not in out
    assert out["interactions_per_s"] > 0 and out["interactions_per_cpu_s"] > 0
    assert out["physics_steps_per_s"] == pytest.approx(out["substeps_per_interaction"] * out["interactions_per_s"])
    assert out["substeps_per_interaction"] == 20  # 500 Hz physics under 25 Hz control
    assert 0 < out["reset_ms_mean"] <= out["reset_ms_max"]
    assert not list(tmp_path.iterdir())  # no log file or output folder where the command was run


def test_dojo_bench_sim_cpu_mode_of_mjx_reports_the_cpu_run(tmp_path):
    result = _bench("modes=[cpu]", "cpu_envs=2", "cpu_steps=3", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    out = json.loads(result.stdout)
    assert out["backend"] == "mujoco" and out["num_envs"] == 2 and out["steps"] == 3  # not mjx's 64 environments


def test_dojo_bench_sim_refuses_mjx_modes_on_the_mujoco_backend(tmp_path):
    result = _bench("backend=mujoco", "modes=[heterogeneous]", cwd=tmp_path)
    assert result.returncode == 1
    assert "heterogeneous and homogeneous are modes of backend=mjx" in result.stderr


def test_streams_and_merged_modes_are_asked_for_by_name_only():
    """`streams` runs MuJoCo Warp (NVIDIA GPUs) and `merged` awaits its GPU figures: the default modes leave them
    out."""
    from dojo.bench.sim_bench import _modes

    assert "streams" not in _modes("mjx", None) and "merged" not in _modes("mjx", None)
    assert _modes("mjx", ["heterogeneous", "streams"]) == ("heterogeneous", "streams")


def test_graph_mode_names_are_checked_on_any_machine_and_ignored_under_jax():
    import jax
    from dojo.backends.mjx.cache import GRAPH_MODES, graph_mode, warp_installed

    assert graph_mode("none", "jax") is None and graph_mode(None, "jax") is None
    if warp_installed() and jax.default_backend() == "cpu":  # Warp's CPU device: plain launches, whatever was asked
        import warp as wp

        assert graph_mode(None, "warp") is graph_mode("warp_staged", "warp") is wp.JaxCallableGraphMode.NONE
    elif warp_installed():
        assert graph_mode(None, "warp") is None  # MJX's own default on a GPU
    with pytest.raises(ValueError, match=r"unknown backend.graph_mode 'warpp'; choose one of .*'warp_staged'"):
        graph_mode("warpp", "jax")
    assert GRAPH_MODES[0] == "none"


def test_streams_modes_refuse_the_jax_implementation(tmp_path):
    result = _bench("backend.impl=jax", "modes=[merged_streams]", cwd=tmp_path)
    assert result.returncode == 1
    assert "'streams' and 'merged_streams' run MuJoCo Warp" in result.stderr


def test_kernel_times_are_asked_of_lanes_on_a_gpu(tmp_path):
    """`kernel_times` times the lanes' kernels with CUDA events: without lanes, or on a CPU, it is refused before
    any plan is compiled, with what to ask for instead."""
    result = _bench("backend.impl=jax", "kernel_times=3", "modes=[heterogeneous]", cwd=tmp_path)
    assert result.returncode == 1 and "kernel_times times the lanes of backend.streams=true" in result.stderr
    import jax

    if jax.default_backend() == "cpu":
        result = _bench("backend.impl=warp", "backend.streams=true", "kernel_times=3", "modes=[heterogeneous]",
                        cwd=tmp_path)
        assert result.returncode == 1 and "kernel_times needs an NVIDIA GPU" in result.stderr


def test_a_lanes_kernels_are_summed_by_name_and_the_costliest_kept():
    from types import SimpleNamespace

    from dojo.backends.mjx.kernel_timing import kernel_table

    launches = [SimpleNamespace(name=n, elapsed=ms) for n, ms in
                [("solve", 0.5), ("collide", 0.25), ("solve", 0.5), ("kinematics", 0.125), ("copy", 0.25)]]
    table = kernel_table(launches, top=2)
    assert table["gpu_ms"] == 1.625 and table["launches"] == 5
    assert table["kernels"] == [{"name": "solve", "ms": 1.0, "launches": 2},
                                {"name": "collide", "ms": 0.25, "launches": 1}]  # ties by name: collide < copy
    assert kernel_table(launches, top=0)["kernels"] == [] and kernel_table([], top=3)["launches"] == 0


def test_jax_reserves_no_gpu_memory_when_only_warp_engines_run_and_streams_get_every_hardware_queue():
    from dojo.bench.sim_bench import gpu_settings

    queues = {"CUDA_DEVICE_MAX_CONNECTIONS": "32"}
    assert gpu_settings(["heterogeneous"]) == {}
    assert gpu_settings(["streams", "merged_streams"]) == {"XLA_PYTHON_CLIENT_PREALLOCATE": "false", **queues}
    assert gpu_settings(["heterogeneous", "streams"]) == {"XLA_PYTHON_CLIENT_MEM_FRACTION": "0.5", **queues}
    assert gpu_settings(["heterogeneous"], engine_streams=True) == {"XLA_PYTHON_CLIENT_MEM_FRACTION": "0.5", **queues}


