"""One demonstration episode as one HDF5 file, streamed to disk step by step.

Layout (T control steps; `action[t]` is the command executed from observation t, i.e. the next-step action):

    /observations/images/<camera>   uint8   [T, H, W, 3]   RGB
    /observations/depth/<camera>    uint16  [T, H, W]      millimetres (when depth is collected)
    /observations/joint_pos         float32 [T, 14]        [left j1..j6, left gripper, right ...]
    /observations/joint_vel         float32 [T, 14]
    /observations/ee_pose           float32 [T, 2, 7]      per arm [x, y, z, qw, qx, qy, qz], arm base frame
    /observations/gripper           float32 [T, 2]         0 closed .. 1 open
    /action                         float32 [T, D]         in the attribute `action_mode`
    /step                           int32   [T]
    attributes: task, instruction, setting, seed, plan_hash, embodiment, action_mode, control_hz, cameras,
                success, num_steps, policy, format

Frames are appended as they are rendered (one gzip-1 chunk per frame: portable, and fast enough to keep up
with rendering), so an episode never has to fit in memory. The file is written as `<name>.tmp.hdf5` and renamed
when the episode is complete: a file with the final name is always a whole episode, which is what resuming a
collection relies on.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

FORMAT = "robodojo-demo/1"
STATE_SHAPES = {"joint_pos": (14,), "joint_vel": (14,), "ee_pose": (2, 7), "gripper": (2,)}


class Hdf5EpisodeWriter:
    """Streams one episode into `path` (see the module docstring for the layout)."""

    def __init__(self, path: Path, cameras: Sequence[str], *, depth: bool, attrs: dict[str, Any]) -> None:
        import h5py

        self.path, self.cameras, self.depth = path, tuple(cameras), depth
        self.tmp = path.with_name(path.stem + ".tmp.hdf5")
        path.parent.mkdir(parents=True, exist_ok=True)
        self._file = h5py.File(self.tmp, "w")
        self._file.attrs.update({"format": FORMAT, "cameras": list(self.cameras), **attrs})
        self._datasets: dict[str, Any] = {}
        self.steps = 0

    def _append(self, name: str, value: np.ndarray, dtype: Any, per_frame_chunk: bool = False) -> None:
        value = np.asarray(value, dtype=dtype)
        ds = self._datasets.get(name)
        if ds is None:
            chunks = (1, *value.shape) if per_frame_chunk else (256, *value.shape)
            options = {"compression": "gzip", "compression_opts": 1} if per_frame_chunk else {}
            ds = self._datasets[name] = self._file.create_dataset(
                name, shape=(0, *value.shape), maxshape=(None, *value.shape), dtype=dtype, chunks=chunks,
                **options)
        ds.resize(self.steps + 1, axis=0)
        ds[self.steps] = value

    def append(self, obs: dict[str, Any], action: np.ndarray) -> None:
        """One step: the observation and the action executed from it."""
        images = obs.get("images", {})
        for camera in self.cameras:
            self._append(f"observations/images/{camera}", images[camera], np.uint8, per_frame_chunk=True)
            if self.depth:
                self._append(f"observations/depth/{camera}", obs["depth"][camera], np.uint16, per_frame_chunk=True)
        for key in STATE_SHAPES:
            self._append(f"observations/{key}", obs["state"][key], np.float32)
        self._append("action", action, np.float32)
        self._append("step", obs.get("meta", {}).get("step", self.steps), np.int32)
        self.steps += 1

    def close(self, **attrs: Any) -> Path:
        """Finish the episode: final attributes, then the file takes its final name."""
        self._file.attrs.update({"num_steps": self.steps, **attrs})
        self._file.close()
        os.replace(self.tmp, self.path)
        return self.path

    def abort(self) -> None:
        """Drop the episode (failed, or interrupted)."""
        self._file.close()
        self.tmp.unlink(missing_ok=True)


def read_episode(path: Path, *, images: bool = True) -> dict[str, Any]:
    """An episode file as plain arrays: `attrs`, `state` (per key), `action`, `step`, and per camera `images`
    (and `depth`) when `images` is true."""
    import h5py

    with h5py.File(path, "r") as f:
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
        obs = f["observations"]
        out: dict[str, Any] = {
            "attrs": attrs,
            "state": {k: obs[k][()] for k in STATE_SHAPES},
            "action": f["action"][()],
            "step": f["step"][()],
        }
        if images:
            out["images"] = {c: obs["images"][c][()] for c in obs["images"]}
            if "depth" in obs:
                out["depth"] = {c: obs["depth"][c][()] for c in obs["depth"]}
    return out
