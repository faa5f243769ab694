"""`dojo collect`: HDF5 episodes and a LeRobot v3.0 dataset that read back, resuming, and auto horizons.

CI-small: the six-step and one-step tasks of tests/recording/pack at 64x48 (CPU rendering costs about a
second per step here). The 100-episode collection is marked slow.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dojo.datagen.collect import auto_horizon, write_horizons

PACK = Path(__file__).resolve().parents[1] / "recording" / "pack"
# dlc_test (training only), horizon_test (in horizon_suite) and open_test (evaluation only): one-step tasks.
COLLECT_PACK = Path(__file__).resolve().parent / "pack"
SMALL = ["policy=zero", "width=64", "height=48", "progress=quiet"]


def dojo(command: str, *args: str, cwd: Path, pack: Path = PACK) -> subprocess.CompletedProcess:
    env = dict(os.environ, DOJO_PLAN_CACHE=str(cwd / "plans"))
    cmd = [sys.executable, "-m", "dojo.cli.main", command, f"packs=[{pack}]", *args]
    return subprocess.run(cmd, check=False, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)


def collect(*args: str, cwd: Path, pack: Path = PACK) -> dict:
    """Run `dojo collect` in a fresh process; return its summary line."""
    result = dojo("collect", *SMALL, *args, cwd=cwd, pack=pack)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


def compiled_horizons(cwd: Path, name: str, *extra: str) -> list[tuple[str, int]]:
    """(hash, horizon) of each plan of the pack's horizon suite, compiled in `cwd`."""
    plans = cwd / f"plans-{name}"
    result = dojo("compile", "suite=horizon_suite", f"out={plans}", *extra, cwd=cwd, pack=COLLECT_PACK)
    assert result.returncode == 0, result.stderr
    index = json.loads((plans / "index.json").read_text())
    return [(e["hash"], json.loads((plans / e["path"]).read_text())["horizon"]) for e in index["plans"]]


@pytest.mark.parametrize(("lengths", "auto_generated", "expected"), [
    ([100] * 10, False, 120),             # 100 x 1.2 exactly: no rounding up past 120
    ([100] * 10, True, 150),
    (list(range(1, 11)), False, 11),      # p90 of 1..10 = 9.1 (linear); 9.1 x 1.2 = 10.92
    (list(range(1, 11)), True, 14),       # 9.1 x 1.5 = 13.65
    ([50, 60, 70, 80, 200], False, 183),  # p90 = 80 + 0.6 x 120 = 152; x 1.2 = 182.4
    ([7], False, 9),                      # 8.4
])
def test_auto_horizon_matches_hand_computation(lengths: list[int], auto_generated: bool, expected: int) -> None:
    assert auto_horizon(lengths, auto_generated) == expected


def test_auto_horizon_needs_demos_and_horizons_file_keeps_other_tasks(tmp_path: Path) -> None:
    with pytest.raises(ValueError):
        auto_horizon([])
    path = tmp_path / "horizons.json"
    write_horizons(path, "a", [10, 20], auto_generated=False)
    write_horizons(path, "b", [100], auto_generated=True)
    data = json.loads(path.read_text())
    assert data["format"] == "robodojo-horizons/1"
    assert data["tasks"]["a"] == {"demo_lengths": [10, 20], "auto_generated": False, "horizon": 23}  # 19 x 1.2
    assert data["tasks"]["b"]["horizon"] == 150


def test_collect_writes_hdf5_and_lerobot_that_read_back(tmp_path: Path) -> None:
    import h5py
    import imageio.v3 as iio
    import pyarrow.parquet as pq

    out = tmp_path / "ds"
    summary = collect("task=short_test", "n=2", "only_success=false", "num_envs=2", f"out={out}", cwd=tmp_path)
    assert summary["kept"] == 2 and summary["frames"] == 12 and "horizon" not in summary  # zero policy: no demos

    files = sorted((out / "hdf5").glob("*.hdf5"))
    assert [f.name for f in files] == ["episode_000000.hdf5", "episode_000001.hdf5"]
    with h5py.File(files[1], "r") as f:
        obs = f["observations"]
        for camera in ("head", "left_wrist", "right_wrist"):
            assert obs["images"][camera].shape == (6, 48, 64, 3) and obs["images"][camera].dtype == np.uint8
            assert obs["depth"][camera].shape == (6, 48, 64) and obs["depth"][camera].dtype == np.uint16
        assert obs["joint_pos"].shape == (6, 14) and obs["joint_vel"].shape == (6, 14)
        assert obs["ee_pose"].shape == (6, 2, 7) and obs["gripper"].shape == (6, 2)
        assert f["action"].shape == (6, 14) and list(f["step"]) == list(range(6))
        assert f.attrs["seed"] == 1_000_001 and len(f.attrs["plan_hash"]) == 64
        assert f.attrs["instruction"] == "Put the red block on the plate." and f.attrs["action_mode"] == "joint"
        assert int(f.attrs["num_steps"]) == 6 and not f.attrs["success"]
        assert np.isfinite(obs["depth"]["head"][()]).all() and obs["depth"]["head"][()].max() > 0

    root = out / "lerobot"
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == 25 and info["robot_type"] == "arx_x5_bimanual"
    assert (info["total_episodes"], info["total_frames"], info["total_tasks"]) == (2, 12, 1)
    assert info["features"]["observation.images.head"]["shape"] == [48, 64, 3]
    assert info["features"]["action"]["shape"] == [14] and len(info["features"]["action"]["names"]) == 14
    data = pq.read_table(root / info["data_path"].format(chunk_index=0, file_index=0)).to_pydict()
    assert data["index"] == list(range(12)) and data["episode_index"] == [0] * 6 + [1] * 6
    assert data["frame_index"] == list(range(6)) * 2 and data["timestamp"][5] == pytest.approx(5 / 25)
    assert len(data["observation.state"][0]) == 14 and len(data["observation.ee_pose"][0]) == 14
    episodes = pq.read_table(root / "meta" / "episodes" / "chunk-000" / "file-000.parquet").to_pylist()
    assert [(e["dataset_from_index"], e["dataset_to_index"], e["length"]) for e in episodes] == [(0, 6, 6), (6, 12, 6)]
    assert episodes[1]["videos/observation.images.head/from_timestamp"] == pytest.approx(6 / 25)
    assert episodes[1]["robodojo/seed"] == 1_000_001 and episodes[0]["tasks"] == ["Put the red block on the plate."]
    tasks = pq.read_table(root / "meta" / "tasks.parquet")
    assert tasks.to_pydict() == {"task_index": [0], "task": ["Put the red block on the plate."]}
    assert json.loads(tasks.schema.metadata[b"pandas"])["index_columns"] == ["task"]  # the index, as pandas reads it
    stats = json.loads((root / "meta" / "stats.json").read_text())
    assert len(stats["action"]["mean"]) == 14 and stats["action"]["count"] == [12]
    assert np.asarray(stats["observation.images.head"]["mean"]).shape == (3, 1, 1)
    for camera in ("head", "left_wrist", "right_wrist"):
        video = root / info["video_path"].format(video_key=f"observation.images.{camera}", chunk_index=0,
                                                 file_index=0)
        assert iio.imread(video).shape == (12, 48, 64, 3)


def test_collect_resumes_keeps_successes_and_writes_horizons(tmp_path: Path) -> None:
    import pyarrow.parquet as pq

    out = tmp_path / "ds"
    args = ("task=settled_test", "cameras=[head]", "depth=false", "num_envs=1", f"out={out}")
    first = collect(*args, "n=2", cwd=tmp_path)
    assert (first["kept"], first["attempted"], first["horizon"]) == (2, 2, 2)  # length 1 x 1.5 (auto-generated)
    files = sorted((out / "hdf5").glob("*.hdf5"))
    stamps = [f.stat().st_mtime_ns for f in files]

    again = collect(*args, "n=2", cwd=tmp_path)
    assert again == first
    shown = dojo("collect", *[a for a in SMALL if not a.startswith("progress=")], "progress=jsonl", *args, "n=2",
                 cwd=tmp_path)
    events = [json.loads(line) for line in (shown.stdout + shown.stderr).splitlines() if line.startswith('{"event"')]
    assert (events[-1]["done"], events[-1]["resumed"], events[-1]["total"]) == (2, 2, 2)  # shown as resumed
    assert [f.stat().st_mtime_ns for f in files] == stamps  # nothing was recorded twice

    more = collect(*args, "n=3", cwd=tmp_path)
    assert (more["kept"], more["attempted"]) == (3, 3)
    assert [f.stat().st_mtime_ns for f in files] == stamps
    horizons = json.loads((tmp_path / "datasets" / "horizons.json").read_text())["tasks"]["settled_test"]
    assert horizons == {"demo_lengths": [1, 1, 1], "auto_generated": True, "horizon": 2}
    episodes = pq.read_table(out / "lerobot" / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    assert episodes.column("robodojo/seed").to_pylist() == [1_000_000, 1_000_001, 1_000_002]


def test_collect_dlc_training_only_task(tmp_path: Path) -> None:
    """DLC tasks are training only: collecting them is their purpose. Their rows (dimension dlc) resume the
    collection but are never scored (tests/runtime/test_episode.py)."""
    import h5py

    from dojo.evaluation.results_store import ResultsStore
    from dojo.report.scoring import score_episodes

    out = tmp_path / "ds"
    args = ("task=dlc_test", "n=2", "cameras=[head]", "num_envs=1", f"out={out}")
    summary = collect(*args, cwd=tmp_path, pack=COLLECT_PACK)
    assert (summary["kept"], summary["attempted"], summary["successes"]) == (2, 2, 2)
    assert summary["horizon"] == 2  # ceil(1 x 1.2): the task has its demos' horizon, though never evaluated
    with h5py.File(out / "hdf5" / "episode_000001.hdf5", "r") as f:
        assert f.attrs["task"] == "dlc_test" and f.attrs["success"] and f.attrs["seed"] == 1_000_001
        assert f["observations/images/head"].shape == (1, 48, 64, 3)
        assert f["observations/depth/head"].shape == (1, 48, 64)
    info = json.loads((out / "lerobot" / "meta" / "info.json").read_text())
    assert (info["total_episodes"], info["total_frames"]) == (2, 2)
    with ResultsStore(out / "collect.sqlite", readonly=True) as store:
        rows = store.rows()
    assert [(r.task, r.dimension, r.success) for r in rows] == [("dlc_test", "dlc", True)] * 2
    try:
        scores = score_episodes(rows)
    except ValueError:  # ScoringError is one: DLC rows alone are nothing to score
        pass
    else:
        raise AssertionError(f"DLC episodes were scored: {scores}")
    assert collect(*args, cwd=tmp_path, pack=COLLECT_PACK) == summary  # and it resumes like any other


def test_collect_refuses_evaluation_only_tasks(tmp_path: Path) -> None:
    result = dojo("collect", *SMALL, "task=open_test", "n=1", f"out={tmp_path / 'ds'}", cwd=tmp_path,
                  pack=COLLECT_PACK)
    assert result.returncode != 0 and "evaluation only" in result.stderr
    assert not (tmp_path / "ds").exists()


def test_collected_horizons_set_the_auto_horizons_of_compiled_suites(tmp_path: Path) -> None:
    """`dojo collect` merges the demo lengths into datasets/horizons.json, which `dojo compile` / `dojo run`
    read by default: the suite's plans get the auto horizon of the collected demos instead of the task's
    fallback, and new plan hashes; `horizons=null` keeps the fallback, a missing `horizons=PATH` is an error."""
    out = tmp_path / "ds"
    compiled_before = compiled_horizons(tmp_path, "before")
    summary = collect("task=horizon_test", "n=2", "cameras=[head]", "depth=false", "num_envs=1", f"out={out}",
                      "format=[hdf5]", cwd=tmp_path, pack=COLLECT_PACK)
    shared = tmp_path / "datasets" / "horizons.json"
    assert summary["horizons"] == "datasets/horizons.json" and summary["horizon"] == 2  # ceil(1 x 1.2)
    horizons = json.loads(shared.read_text())
    assert horizons["tasks"]["horizon_test"] == {"demo_lengths": [1, 1], "auto_generated": False, "horizon": 2}

    with_demos = compiled_horizons(tmp_path, "auto")
    fallback = compiled_horizons(tmp_path, "null", "horizons=null")
    assert [h for _, h in with_demos] == [2, 2]
    assert [h for _, h in fallback] == [h for _, h in compiled_before] == [6, 6]
    assert compiled_horizons(tmp_path, "path", f"horizons={shared}") == with_demos
    missing = dojo("compile", "suite=horizon_suite", f"out={tmp_path / 'x'}", "horizons=nowhere.json", cwd=tmp_path,
                   pack=COLLECT_PACK)
    assert missing.returncode != 0 and "horizons=nowhere.json: no such file" in missing.stderr
    assert not {d for d, _ in with_demos} & {d for d, _ in fallback}


@pytest.mark.slow
def test_collect_dlc_with_the_oracle(tmp_path: Path) -> None:
    """The real DLC task, demonstrated by its scripted expert (one episode, one small camera)."""
    out = tmp_path / "ds"
    summary = collect("task=dlc", "n=1", "max_attempts=2", "policy=oracle", "cameras=[head]", "depth=false",
                      "num_envs=1", f"out={out}", cwd=tmp_path)
    assert summary["kept"] == 1 and summary["horizon"] > 0
    info = json.loads((out / "lerobot" / "meta" / "info.json").read_text())
    assert info["total_episodes"] == 1 and info["total_frames"] == summary["frames"]


@pytest.mark.slow
def test_collect_100_episodes(tmp_path: Path) -> None:
    """The issue's done-when: a 100-episode collection opens with h5py and as a LeRobot layout."""
    import h5py

    out = tmp_path / "ds"
    summary = collect("task=short_test", "n=100", "only_success=false", "num_envs=8", f"out={out}", cwd=tmp_path)
    assert summary["kept"] == 100
    for path in sorted((out / "hdf5").glob("*.hdf5")):
        with h5py.File(path, "r") as f:
            assert f["action"].shape[0] == f["observations/images/head"].shape[0]
    assert json.loads((out / "lerobot" / "meta" / "info.json").read_text())["total_episodes"] == 100
