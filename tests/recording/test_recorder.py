"""Recording: `dojo run record=head` films each episode (instruction and step counter drawn on) into a playable
MP4 linked from its result row, and saves a trajectory that XPolicyLab's replay policy plays back exactly.

The pack beside this file has a six-step task, so that a recorded run stays CI-small: CPU rendering costs
about a second per step here.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from dojo.compiler.episodes import PlannedEpisode
from dojo.evaluation.evaluate import _Slot, _with_episode
from dojo.evaluation.recorder import overlay, record_cameras, tile
from dojo.evaluation.results_store import ResultsStore

PACK = Path(__file__).resolve().parent / "pack"
CAMERAS = ["head", "left_wrist", "right_wrist"]


def test_record_modes_choose_cameras() -> None:
    assert record_cameras("none", CAMERAS) == ()
    assert record_cameras("head", CAMERAS) == ("head",)
    assert record_cameras("all", CAMERAS) == tuple(CAMERAS)
    with pytest.raises(ValueError, match="record must be one of"):
        record_cameras("wrist", CAMERAS)


def test_overlay_draws_on_a_copy_and_tile_keeps_camera_order() -> None:
    frame = np.zeros((48, 64, 3), np.uint8)
    drawn = overlay(frame, "Put the red block on the plate.", 3, 6)
    assert drawn.shape == frame.shape and drawn.any() and not frame.any()
    images = {c: np.full((4, 5, 3), k, np.uint8) for k, c in enumerate(CAMERAS)}
    tiled = tile(images, ["right_wrist", "head"])
    assert tiled.shape == (4, 10, 3) and tiled[0, 0, 0] == 2 and tiled[0, 9, 0] == 0
    with pytest.raises(KeyError, match="left_wrist"):
        tile({"head": images["head"]}, ["head", "left_wrist"])


def test_policy_sees_only_its_own_cameras() -> None:
    item = PlannedEpisode("t", "precision", "standard", 7, 0, 7, plan_hash="h", plan_path=Path("p.json"))
    obs = {"images": {"head": np.zeros((2, 2, 3))}, "state": {}, "meta": {"episode": 7}}
    slot = _Slot(item, plan=None, started=0.0)  # type: ignore[arg-type]
    assert "images" not in _with_episode(obs, slot, ())
    assert set(_with_episode(obs, slot, ("head",))["images"]) == {"head"}
    assert "images" in obs  # the recorder still gets the frame


def test_run_record_head_writes_playable_video_and_replayable_trajectory(tmp_path: Path) -> None:
    import imageio.v3 as iio
    from dojo.backends.mujoco.backend import MujocoBackend
    from dojo.compiler.plan import Plan

    from xpolicylab.policies import load_policy

    env = dict(os.environ, DOJO_PLAN_CACHE=str(tmp_path / "plans"))
    cmd = [sys.executable, "-m", "dojo.cli.main", "run", f"packs=[{PACK}]", "suite=short_suite", "episodes=1",
           "num_envs=1", "policy=random", "width=64", "height=48", "record=head", "progress=quiet",
           f"results={tmp_path / 'r.sqlite'}"]
    result = subprocess.run(cmd, check=False, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr

    with ResultsStore(tmp_path / "r.sqlite", readonly=True) as store:
        (row,) = store.rows()
    assert row.video_path and not os.path.isabs(row.video_path)  # relative to the store: the report resolves it
    video = tmp_path / row.video_path
    assert video.parent.parent.name == "videos" and video.suffix == ".mp4"
    frames = iio.imread(video)
    assert frames.shape == (row.steps + 1, 48, 64, 3)  # one frame per action, plus the last observation
    assert not list(tmp_path.rglob("*.tmp.*"))

    trajectory = Path(str(video).replace("/videos/", "/trajectories/")).with_suffix(".npz")
    with np.load(trajectory) as data:
        recorded = {k: data[k] for k in data.files}
    assert recorded["actions"].shape == (row.steps, 14) and recorded["joint_pos"].shape == (row.steps, 14)
    assert recorded["ee_pose"].shape == (row.steps, 2, 7) and list(recorded["step"]) == list(range(row.steps))
    assert str(recorded["plan_hash"]) == row.plan_hash and int(recorded["seed"]) == row.scene_seed

    replay = load_policy("replay", {"episode": str(trajectory), "chunk_size": row.steps})
    replay.update_obs_batch([{}], [0])
    np.testing.assert_array_equal(replay.get_action_batch([0])[0], recorded["actions"])

    (plan_file,) = (tmp_path / "plans").rglob(f"*-{row.plan_hash[:16]}.json")
    with MujocoBackend(num_threads=1) as backend:  # no cameras: replaying needs no rendering
        backend.load([Plan.load(plan_file)])
        states = [backend.reset([0])[0]["state"]["joint_pos"]]
        for action in recorded["actions"][:-1]:
            states.append(backend.step(action[None], [0]).obs[0]["state"]["joint_pos"])
    np.testing.assert_array_equal(np.stack(states), recorded["joint_pos"])
