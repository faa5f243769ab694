"""Recording evaluation episodes: an MP4 per episode with the instruction and step counter drawn on it, and the
trajectory (states, actions) as a compressed `.npz` that XPolicyLab's `replay` policy plays back.

The evaluation loop owns one recorder per environment slot and drives it with `start` (a slot got a new
episode), `add` (the observation an action was chosen from, and that action), `finish` (the episode ended; the
files are moved into place and their paths returned for the result row) and `discard` (the run stopped with
the episode unfinished). Files are written under temporary names and renamed on `finish`, so a killed run
never leaves a truncated video behind a recorded row; a resumed run records the lost episodes again.

Videos are H.264 (yuv420p, the format every browser and player decodes) through imageio's ffmpeg, which ships
its own binary. Recording asks the backend only for the cameras it records (plus the policy's own): rendering
is the expensive part of a step.
"""

from __future__ import annotations

import os
import textwrap
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

if TYPE_CHECKING:
    from dojo.compiler.plan import Plan

    from dojo.compiler.episodes import PlannedEpisode

RECORD_MODES = ("none", "head", "all")
STATE_KEYS = ("joint_pos", "joint_vel", "ee_pose", "gripper")


class SlotRecorder(Protocol):
    """What the evaluation loop calls on the recorder of one slot."""

    def start(self, item: PlannedEpisode, plan: Plan) -> None:
        """A new episode starts in this slot."""

    def add(self, obs: dict[str, Any], action: np.ndarray) -> None:
        """One control step: the observation the action was chosen from, and the action executed."""

    def finish(self, last_obs: dict[str, Any], success: bool) -> tuple[str | None, str | None]:
        """The episode ended with `last_obs`; returns (video path, trajectory path) as stored in its row."""

    def discard(self) -> None:
        """Drop an unfinished episode's files."""


def record_cameras(mode: str, robot_cameras: Sequence[str]) -> tuple[str, ...]:
    """The cameras `record=<mode>` films: none, the head camera, or every camera of the robot."""
    if mode not in RECORD_MODES:
        raise ValueError(f"record must be one of {RECORD_MODES}, got {mode!r}")
    if mode == "none":
        return ()
    if mode == "head":
        if "head" not in robot_cameras:
            raise ValueError(f"record=head: the robot has no head camera (cameras: {list(robot_cameras)})")
        return ("head",)
    return tuple(robot_cameras)


class Mp4Writer:
    """H.264 MP4 written frame by frame to `<path>.tmp.mp4` and renamed to `path` on `close`.

    `gop` sets the keyframe interval: small for datasets that are read at random frames, ffmpeg's default for
    videos that are watched.
    """

    def __init__(self, path: Path, fps: float, *, crf: int = 23, gop: int | None = None) -> None:
        import imageio.v2 as imageio

        # imageio-ffmpeg starts ffmpeg with a `preexec_fn` (to keep Ctrl-C away from it), which runs Python in the
        # forked child before exec: unsafe in a multithreaded process (JAX, MuJoCo's pools, the live display).
        # Without it ffmpeg is spawned the safe way; a Ctrl-C then also stops ffmpeg, and `abort` copes.
        os.environ.setdefault("IMAGEIO_FFMPEG_NO_PREVENT_SIGINT", "1")
        self.path = path
        self.tmp = path.with_name(path.stem + ".tmp.mp4")
        path.parent.mkdir(parents=True, exist_ok=True)
        params = ["-crf", str(crf), "-preset", "veryfast"] + (["-g", str(gop)] if gop else [])
        # macro_block_size=2: yuv420p needs even sizes only; the default (16) would rescale 640x360 and the like.
        self._writer = imageio.get_writer(str(self.tmp), format="FFMPEG", fps=fps, codec="libx264", quality=None,
                                          pixelformat="yuv420p", macro_block_size=2, ffmpeg_params=params,
                                          ffmpeg_log_level="error")
        self.frames = 0

    def write(self, frame: np.ndarray) -> None:
        self._writer.append_data(np.ascontiguousarray(frame, dtype=np.uint8))
        self.frames += 1

    def close(self) -> Path:
        self._writer.close()
        os.replace(self.tmp, self.path)
        return self.path

    def abort(self) -> None:
        try:
            self._writer.close()
        except OSError:  # ffmpeg already stopped (a Ctrl-C reaches it too): the file is dropped anyway
            pass
        self.tmp.unlink(missing_ok=True)


@lru_cache(maxsize=8)
def _font(size: int) -> Any:
    """Pillow's bundled font at `size` pixels (loaded once per size, not per frame)."""
    from PIL import ImageFont

    return ImageFont.load_default(size=size)


def overlay(frame: np.ndarray, instruction: str, step: int, horizon: int, status: str = "") -> np.ndarray:
    """The frame with the instruction (wrapped, on a dark band at the top) and `step t/T` at the bottom."""
    from PIL import Image, ImageDraw

    image = Image.fromarray(frame)
    height, width = frame.shape[:2]
    size = max(8, height // 24)
    font = _font(size)
    draw = ImageDraw.Draw(image, "RGBA")
    chars = max(8, int(width / (0.55 * size)))
    lines = textwrap.wrap(instruction, chars)[:3]
    band = (len(lines) * (size + 2)) + 4
    draw.rectangle((0, 0, width, band), fill=(0, 0, 0, 140))
    for k, line in enumerate(lines):
        draw.text((4, 2 + k * (size + 2)), line, font=font, fill=(255, 255, 255, 255))
    counter = f"step {step}/{horizon}" + (f"  {status}" if status else "")
    draw.rectangle((0, height - size - 6, width, height), fill=(0, 0, 0, 140))
    draw.text((4, height - size - 4), counter, font=font, fill=(255, 255, 255, 255))
    return np.asarray(image)


def tile(images: dict[str, np.ndarray], cameras: Sequence[str]) -> np.ndarray:
    """The cameras side by side, left to right in `cameras` order (one video holds them all)."""
    missing = [c for c in cameras if c not in images]
    if missing:
        raise KeyError(f"observation has no image from camera(s) {missing}; rendered: {sorted(images)}")
    return np.concatenate([images[c] for c in cameras], axis=1)


def episode_stem(item: PlannedEpisode) -> str:
    """A file name unique inside a run: task, setting, scene seed, evaluation seed and episode number."""
    return f"{item.task}/{item.setting}-{item.scene_seed}-s{item.eval_seed}-e{item.episode}"


class EpisodeRecorder:
    """Records one slot's episodes under `out_dir`: `videos/<task>/<episode>.mp4` (the `cameras` side by side,
    annotated) and `trajectories/<task>/<episode>.npz`. Returned paths are relative to `relative_to` when given
    (the results store's folder, against which reports resolve them)."""

    def __init__(self, out_dir: Path, cameras: Sequence[str], *, action_mode: str,
                 relative_to: Path | None = None) -> None:
        if not cameras:
            raise ValueError("EpisodeRecorder needs at least one camera (record=none records nothing)")
        self.out_dir, self.cameras, self.action_mode = out_dir, tuple(cameras), action_mode
        self.relative_to = relative_to
        self._item: PlannedEpisode | None = None
        self._plan: Plan | None = None
        self._video: Mp4Writer | None = None
        self._states: dict[str, list[np.ndarray]] = {}
        self._actions: list[np.ndarray] = []
        self._steps: list[int] = []

    def start(self, item: PlannedEpisode, plan: Plan) -> None:
        self.discard()
        self._item, self._plan = item, plan
        self._video = Mp4Writer(self.out_dir / "videos" / f"{episode_stem(item)}.mp4", plan.control_hz)
        self._states = {k: [] for k in STATE_KEYS}
        self._actions, self._steps = [], []

    def _frame(self, obs: dict[str, Any], status: str = "") -> None:
        assert self._video is not None and self._plan is not None
        step = int(obs.get("meta", {}).get("step", len(self._steps)))
        self._video.write(overlay(tile(obs.get("images", {}), self.cameras), self._plan.instruction, step,
                                  self._plan.horizon, status))

    def add(self, obs: dict[str, Any], action: np.ndarray) -> None:
        self._frame(obs)
        for key in STATE_KEYS:
            self._states[key].append(np.asarray(obs["state"][key], dtype=np.float32))
        self._actions.append(np.asarray(action, dtype=np.float32))
        self._steps.append(int(obs.get("meta", {}).get("step", len(self._steps))))

    def finish(self, last_obs: dict[str, Any], success: bool) -> tuple[str | None, str | None]:
        if self._video is None or self._item is None or self._plan is None:
            raise RuntimeError("EpisodeRecorder.finish without start")
        self._frame(last_obs, "success" if success else "")
        video = self._video.close()
        self._video = None
        trajectory = self.out_dir / "trajectories" / f"{episode_stem(self._item)}.npz"
        save_trajectory(trajectory, self._item, self._plan, self._states, self._actions, self._steps,
                        action_mode=self.action_mode, success=success)
        return self._link(video), self._link(trajectory)

    def discard(self) -> None:
        if self._video is not None:
            self._video.abort()
            self._video = None

    def _link(self, path: Path) -> str:
        return os.path.relpath(path, self.relative_to) if self.relative_to is not None else str(path)


def save_trajectory(path: Path, item: PlannedEpisode, plan: Plan, states: dict[str, list[np.ndarray]],
                    actions: list[np.ndarray], steps: list[int], *, action_mode: str, success: bool) -> None:
    """Write the replay file: `actions` [T, D] with `action_mode` and `embodiment` (what XPolicyLab's replay
    policy reads), the states the actions were chosen from, and the episode's identity. Atomic (tmp + rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    dim = len(actions[0]) if actions else 0
    arrays: dict[str, Any] = {
        "actions": np.asarray(actions, dtype=np.float32).reshape(len(actions), dim),
        "step": np.asarray(steps, dtype=np.int32),
        **{k: np.asarray(v, dtype=np.float32) for k, v in states.items()},
        "action_mode": np.array(action_mode), "embodiment": np.array(plan.embodiment),
        "plan_hash": np.array(plan.hash), "task": np.array(plan.task), "setting": np.array(plan.setting),
        "instruction": np.array(plan.instruction), "seed": np.array(plan.seed, dtype=np.int64),
        "eval_seed": np.array(item.eval_seed, dtype=np.int64), "episode": np.array(item.episode, dtype=np.int64),
        "control_hz": np.array(plan.control_hz, dtype=np.float64), "success": np.array(success),
    }
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)
