"""Several devices in one process: the engine splits every bucket's batch over the local devices.

JAX fixes its device count when it starts, so the comparison runs in a child process with four forced CPU host
devices (`--xla_force_host_platform_device_count=4`): the same toy buckets stepped on one device and split over
four must give the same trajectories bit for bit, each compiling its tick once. The child runs Eigen single-
threaded (`--xla_cpu_multi_thread_eigen=false`): its multi-threaded sums are split by the threads a device gets,
which moves the last float32 bits (see `dojo.backends.mjx.sharding`); the backend-level run (slow test) compares
success and scores under the default flags.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parent
DEVICES = 4
TICKS = 6


def compare_on_devices(count: int) -> dict:
    """Run in the child: the same ticks on 1 device and on `count`; what each produced."""
    import jax

    from conftest import CACHE_DIR, toy_plan
    from dojo.backends.mjx.batch import Engine
    from dojo.backends.mjx.bucket import make_buckets
    from dojo.backends.mjx.cache import enable_compilation_cache
    from dojo.backends.mjx.sharding import Placement, local_devices

    enable_compilation_cache(CACHE_DIR)
    buckets = make_buckets([toy_plan(seed=s) for s in range(3)])  # one bucket; every bucket is split alike
    wide = Placement.over(local_devices(count), "jax")
    sizes = [wide.padded(9)]  # 12: 3 rows a device, a whole multiple of 4
    out: dict = {"sizes": sizes, "visible": len(jax.devices()), "runs": {}}
    for n in (1, count):
        engine = Engine(buckets, sizes, "jax", placement=Placement.over(local_devices(n), "jax"))
        members = [np.arange(size) % len(b.members) for b, size in zip(buckets, sizes)]
        every, none = [np.ones(s, bool) for s in sizes], [np.zeros(s, bool) for s in sizes]
        engine.tick(members, every, none, [np.zeros((s, b.model.nu), np.float32) for b, s in zip(buckets, sizes)])
        trajectory = []
        for t in range(TICKS):
            resets = [np.arange(s) == 3 * t % s for s in sizes]  # one env per tick starts another member's episode
            for m, r, b in zip(members, resets, buckets):
                m[r] = (m[r] + 1) % len(b.members)
            ctrl = [np.full((s, b.model.nu), 0.2 if t % 2 else -0.1, np.float32) for b, s in zip(buckets, sizes)]
            engine.tick(members, resets, every, ctrl)
            trajectory.append([[np.asarray(d.qpos).tolist(), np.asarray(d.qvel).tolist()] for d in engine.data])
        out["runs"][n] = {"trajectory": trajectory, "compilations": engine.compilations(),
                          "devices_holding_state": [len(d.qpos.sharding.device_set) for d in engine.data],
                          "shard_rows": [d.qpos.addressable_shards[0].data.shape[0] for d in engine.data]}
    return out


@pytest.fixture(scope="module")
def sharded() -> dict:
    flags = f"--xla_force_host_platform_device_count={DEVICES} --xla_cpu_multi_thread_eigen=false"
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    code = f"import json, test_sharding; print(json.dumps(test_sharding.compare_on_devices({DEVICES})))"
    result = subprocess.run([sys.executable, "-c", code], cwd=HERE, env=env, capture_output=True, text=True,
                            timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_four_devices_step_exactly_what_one_device_steps(sharded: dict) -> None:
    one, four = sharded["runs"]["1"], sharded["runs"][str(DEVICES)]
    assert sharded["visible"] == DEVICES
    assert one["trajectory"] == four["trajectory"]  # bit for bit, every tick, refills included
    qpos = np.asarray(one["trajectory"][-1][0][0])
    assert len({tuple(row) for row in qpos}) > 2  # the envs really differ (members, resets at different ticks)


def test_each_batch_lies_split_over_every_device_and_compiles_once(sharded: dict) -> None:
    one, four = sharded["runs"]["1"], sharded["runs"][str(DEVICES)]
    assert sharded["sizes"] == [12]
    assert one["devices_holding_state"] == [1] and four["devices_holding_state"] == [DEVICES]
    assert four["shard_rows"] == [3]
    assert one["compilations"] == four["compilations"] == 1


def test_placement_pads_batches_to_the_device_count_and_names_the_fix() -> None:
    from dojo.backends.mjx.sharding import Placement, local_devices

    from jax.sharding import Mesh

    one = Placement.over(local_devices(), "jax")
    assert [one.padded(n) for n in (0, 1, 5)] == [1, 1, 5]
    four = Placement(Mesh(np.asarray(local_devices() * 4), ("envs",)))  # the arithmetic only: never put arrays
    assert [four.padded(n) for n in (1, 8, 9)] == [8, 8, 12]
    with pytest.raises(ValueError, match=r"batch sizes \[6\] do not split over 4 devices: .* 6 -> 8"):
        four.check([8, 6])
    with pytest.raises(ValueError, match="devices=99: this process sees"):
        local_devices(99)
    with pytest.raises(ValueError, match="a number of devices or 'all'"):
        local_devices("two")


SHARD_TASK = """kind: task
version: 1
id: shard_place
dimension: generalization
embodiment: arx_x5_bimanual
instruction: Put the block on the plate.
settings: {standard: {clutter: [0, 0]}}
scene:
  regions:
    left: {center: [-0.2, 0.0], size: [0.2, 0.2]}
    right: {center: [0.2, 0.0], size: [0.2, 0.2]}
  objects:
    - {name: block, asset: {category: test_block}, region: left, color: red}
    - {name: plate, asset: test_plate, region: right}
success: {on: [block, plate]}
stages:
  - {name: standing, when: {upright: block}}
  - {name: close, when: {near: [block, plate, 0.4]}}
  - {name: placed, when: {on: [block, plate]}, weight: 2}
horizon: 4
"""
SHARD_SUITE = """kind: suite
version: 1
id: shard_mix
tasks: [shard_place]
episodes: 8
seeds: [0]
generalization_split: {standard: 1.0}
"""
"""The slow test's pack: the test pack's block and plate, standard scenes only (one bucket: random ones add clutter
meshes), 4 control steps. Its layouts differ in the block's distance to the plate, so episodes 0-2 and 7 reach
the `close` stage at their first step (score 50) and the others never do (25): a row stepped in the wrong
environment shows."""


@pytest.mark.slow
def test_dojo_run_on_four_devices_records_what_one_device_records(tmp_path: Path) -> None:
    """The user's command: `dojo run backend=mjx` with 8 environments split over 4 CPU devices and on 1 (the
    default XLA flags, Eigen multi-threaded), the privileged oracle: the same episodes, each with the same success,
    score, steps and stage times. 43 minutes on the 2-core machine (2026-11-27): 16 on 4 devices, 27 on 1, about
    2.5 of them XLA's compile, the rest the CPU stepping MJX's `jax` implementation."""
    from dojo.evaluation.results_store import ResultsStore

    from conftest import write_pack

    pack = write_pack(tmp_path, {"shard_place.yaml": SHARD_TASK}, {"shard_mix.yaml": SHARD_SUITE})
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={DEVICES}", JAX_PLATFORMS="cpu",
               DOJO_OUTPUTS=str(tmp_path / "outputs"))
    rows = {}
    for n in (DEVICES, 1):
        store = tmp_path / f"devices{n}.sqlite"
        done = subprocess.run([sys.executable, "-m", "dojo.cli.main", "run", "backend=mjx", f"backend.devices={n}",
                               f"packs=[{pack}]", "suite=shard_mix", "num_envs=8", "progress=quiet",
                               f"plans={tmp_path / 'plans'}", f"results={store}"], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=3600)
        assert done.returncode == 0, done.stderr[-3000:]
        assert f"environments split over {n} cpu device(s)" in done.stderr
        with ResultsStore(store, readonly=True) as results:
            rows[n] = {r.key: (r.success, r.score, r.steps, r.stage_times) for r in results.rows()}
    assert len(rows[1]) == 8
    assert rows[DEVICES] == rows[1]
    assert sorted({round(score, 3) for _, score, _, _ in rows[1].values()}) == [25.0, 50.0]


def test_bench_reports_each_device_count_with_its_speedup_and_drift() -> None:
    from dojo.bench.sim_bench import _by_devices, _device_counts

    assert _device_counts("all") == _device_counts(None) == [1] and _device_counts([1, "all"]) == [1]
    qpos = np.zeros((8, 3), np.float32)
    runs = {1: {"seconds": 2.0, "setup_s": 5.0, "interactions": 80, "physics_steps": 800, "compilations": 1,
                "qpos": [qpos]},
            4: {"seconds": 1.0, "setup_s": 6.0, "interactions": 80, "physics_steps": 800, "compilations": 1,
                "qpos": [qpos + np.float32(1e-6)]}}
    out = _by_devices(runs)
    assert out["1"]["speedup_over_1"] == 1.0 and out["4"]["speedup_over_1"] == 2.0
    assert out["1"]["max_qpos_difference_from_1"] == 0.0
    assert out["4"]["max_qpos_difference_from_1"] == pytest.approx(1e-6, rel=1e-3)
