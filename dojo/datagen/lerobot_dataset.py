"""Demonstrations as a LeRobot v3.0 dataset, built from the collected HDF5 episodes.

The layout is LeRobot's `codebase_version: v3.0` (many episodes per file, relational episode metadata):

    meta/info.json                                   fps, features, path templates, totals
    meta/stats.json                                  per feature min/max/mean/std/count (+ quantiles)
    meta/tasks.parquet                               task string (the index) -> task_index
    meta/episodes/chunk-000/file-000.parquet         per episode: length, tasks, data and video offsets, stats
    data/chunk-000/file-000.parquet                  one row per frame
    videos/observation.images.<camera>/chunk-000/file-000.mp4   the episodes of a camera back to back

Files roll over at LeRobot's default sizes (100 MB of data, 200 MB of video per file; 1000 files per chunk).
Videos are H.264 yuv420p (a codec LeRobot accepts) with a keyframe every 2 frames, as LeRobot encodes, so that
any frame decodes quickly. Depth stays in the HDF5 episodes: LeRobot's MP4 features are 8-bit colour, and
millimetre depth would not survive that. RoboDojo's own episode identity (scene seed, plan hash, setting,
success) rides along as extra `robodojo/...` columns of the episode metadata.

The dataset is rebuilt as a whole into `<root>.tmp` and then swapped in, so readers never see half of one.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import shutil
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from dojo.datagen.hdf5_episode import read_episode
from dojo.evaluation.recorder import Mp4Writer

CODEBASE_VERSION = "v3.0"
CHUNKS_SIZE = 1000
DATA_FILES_SIZE_IN_MB = 100
VIDEO_FILES_SIZE_IN_MB = 200
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_GOP = 2
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
IMAGE_STATS_FRAMES = 100  # frames per episode sampled for image statistics
IMAGE_STATS_SIDE = 150    # and downsampled to about this many pixels on the long side
READ_BLOCK = 32           # frames read from HDF5 at a time while encoding
DEFAULT_FEATURES = ("timestamp", "frame_index", "episode_index", "index", "task_index")


def _next_file(chunk: int, file: int) -> tuple[int, int]:
    """LeRobot's file numbering: file indices run up to CHUNKS_SIZE, then the next chunk starts."""
    return (chunk + 1, 0) if file + 1 >= CHUNKS_SIZE else (chunk, file + 1)


def state_names(embodiment: str) -> dict[str, list[str]]:
    """Names of every element of the state features and of both action layouts, per arm."""
    from xpolicylab.embodiments import ARMS, get_embodiment

    joints = get_embodiment(embodiment).joints_per_arm
    joint = [f"{arm}_{name}" for arm in ARMS for name in [*(f"joint_{j + 1}" for j in range(joints)), "gripper"]]
    pose = [f"{arm}_{c}" for arm in ARMS for c in ("x", "y", "z", "qw", "qx", "qy", "qz")]
    return {"joint": joint, "ee_pose": pose, "gripper": [f"{arm}_gripper" for arm in ARMS],
            "ee": [f"{arm}_{c}" for arm in ARMS for c in ("x", "y", "z", "qw", "qx", "qy", "qz", "gripper")]}


def _numeric_features(embodiment: str, action_mode: str, action_dim: int) -> dict[str, dict[str, Any]]:
    names = state_names(embodiment)
    return {
        "observation.state": {"dtype": "float32", "shape": [len(names["joint"])], "names": names["joint"]},
        "observation.velocity": {"dtype": "float32", "shape": [len(names["joint"])], "names": names["joint"]},
        "observation.ee_pose": {"dtype": "float32", "shape": [len(names["ee_pose"])], "names": names["ee_pose"]},
        "observation.gripper": {"dtype": "float32", "shape": [2], "names": names["gripper"]},
        "action": {"dtype": "float32", "shape": [action_dim], "names": names["joint" if action_mode == "joint"
                                                                          else "ee"]},
    }


def _episode_columns(episode: dict[str, Any]) -> dict[str, np.ndarray]:
    """The numeric features of one episode, [T, dim] float32 each."""
    state, steps = episode["state"], len(episode["action"])
    return {
        "observation.state": state["joint_pos"].reshape(steps, -1),
        "observation.velocity": state["joint_vel"].reshape(steps, -1),
        "observation.ee_pose": state["ee_pose"].reshape(steps, -1),
        "observation.gripper": state["gripper"].reshape(steps, -1),
        "action": episode["action"].reshape(steps, -1),
    }


def numeric_stats(values: np.ndarray) -> dict[str, np.ndarray]:
    """LeRobot's statistics of a [N, dim] feature: min, max, mean, std, count and quantiles per element."""
    values = np.asarray(values, dtype=np.float64)
    stats = {"min": values.min(0), "max": values.max(0), "mean": values.mean(0), "std": values.std(0),
             "count": np.array([len(values)])}
    for q in QUANTILES:
        stats[f"q{round(q * 100):02d}"] = np.quantile(values, q, axis=0)
    return stats


def image_stats(frames: np.ndarray) -> dict[str, np.ndarray]:
    """Per-channel statistics of sampled frames [N, H, W, 3] in [0, 1], shaped [3, 1, 1] as LeRobot keeps them;
    `count` is the number of frames sampled."""
    x = frames.astype(np.float64) / 255.0
    axes = (0, 1, 2)

    def channel(v: np.ndarray) -> np.ndarray:
        return v.reshape(3, 1, 1)

    return {"min": channel(x.min(axes)), "max": channel(x.max(axes)), "mean": channel(x.mean(axes)),
            "std": channel(x.std(axes)), "count": np.array([len(frames)])}


def aggregate_image_stats(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Dataset statistics from per-episode ones: count-weighted mean and pooled variance."""
    counts = np.array([p["count"][0] for p in parts], dtype=np.float64)
    means = np.stack([p["mean"] for p in parts])
    weights = (counts / counts.sum()).reshape(-1, 1, 1, 1)
    mean = (weights * means).sum(0)
    var = (weights * (np.stack([p["std"] for p in parts]) ** 2 + (means - mean) ** 2)).sum(0)
    return {"min": np.min([p["min"] for p in parts], 0), "max": np.max([p["max"] for p in parts], 0),
            "mean": mean, "std": np.sqrt(var), "count": np.array([int(counts.sum())])}


def _fixed_lists(values: np.ndarray) -> Any:
    import pyarrow as pa

    values = np.ascontiguousarray(values, dtype=np.float32)
    return pa.FixedSizeListArray.from_arrays(pa.array(values.reshape(-1)), values.shape[1])


def _tasks_table(tasks: list[str]) -> Any:
    """`meta/tasks.parquet` as LeRobot writes it with pandas: the task string is the index, `task_index` the
    column (pandas metadata included, so `pd.read_parquet` gives the same frame back)."""
    import pyarrow as pa

    pandas_meta = {
        "index_columns": ["task"], "column_indexes": [],
        "columns": [{"name": "task_index", "field_name": "task_index", "pandas_type": "int64",
                     "numpy_type": "int64", "metadata": None},
                    {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object",
                     "metadata": None}],
        "creator": {"library": "pyarrow", "version": pa.__version__}, "pandas_version": "2.2.0",
    }
    table = pa.table({"task_index": pa.array(range(len(tasks)), pa.int64()), "task": pa.array(tasks, pa.string())})
    return table.replace_schema_metadata({b"pandas": json.dumps(pandas_meta).encode()})


def _episode_row_table(rows: list[dict[str, Any]]) -> Any:
    """Episode metadata: scalars as they are, statistics arrays as (nested) lists."""
    import pyarrow as pa

    def plain(v: Any) -> Any:
        return v.tolist() if isinstance(v, np.ndarray) else v

    return pa.Table.from_pylist([{k: plain(v) for k, v in row.items()} for row in rows])


class _VideoFiles:
    """The MP4 files of one camera: episodes appended back to back, a new file past the size limit."""

    def __init__(self, root: Path, key: str, fps: int) -> None:
        self.root, self.key, self.fps = root, key, fps
        self.chunk, self.file, self.frames = 0, 0, 0
        self.writer: Mp4Writer | None = None

    def _path(self) -> Path:
        return self.root / VIDEO_PATH.format(video_key=self.key, chunk_index=self.chunk, file_index=self.file)

    def _written_bytes(self) -> int:
        """What ffmpeg has written so far (it creates the file only once its encoder has started)."""
        assert self.writer is not None
        return self.writer.tmp.stat().st_size if self.writer.tmp.exists() else 0

    def append(self, dataset: Any) -> tuple[dict[str, Any], np.ndarray]:
        """Write an episode's frames (an HDF5 dataset, read once, in blocks); returns its `videos/<key>/...`
        episode columns and up to IMAGE_STATS_FRAMES evenly spaced frames, spatially strided, for statistics."""
        if self.writer is not None and self._written_bytes() > VIDEO_FILES_SIZE_IN_MB * 2**20:
            self.writer.close()
            self.writer, self.frames = None, 0
            self.chunk, self.file = _next_file(self.chunk, self.file)
        if self.writer is None:
            self.writer = Mp4Writer(self._path(), self.fps, gop=VIDEO_GOP)
        steps, height, width = dataset.shape[:3]
        stride = max(1, max(height, width) // IMAGE_STATS_SIDE)
        sampled = set(np.linspace(0, steps - 1, min(steps, IMAGE_STATS_FRAMES)).round().astype(int).tolist())
        samples, start = [], self.frames
        for first in range(0, steps, READ_BLOCK):
            for t, frame in enumerate(dataset[first:first + READ_BLOCK], first):
                self.writer.write(frame)
                if t in sampled:
                    samples.append(frame[::stride, ::stride])
        self.frames += steps
        prefix = f"videos/{self.key}/"
        return ({prefix + "chunk_index": self.chunk, prefix + "file_index": self.file,
                 prefix + "from_timestamp": start / self.fps, prefix + "to_timestamp": self.frames / self.fps},
                np.stack(samples))

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


def _encode_camera(root: Path, camera: str, episodes: Sequence[Path], fps: int
                   ) -> tuple[list[dict[str, Any]], list[dict[str, np.ndarray]], tuple[int, ...]]:
    """One camera's videos over all episodes (run in its own process: decompressing the HDF5 frames and
    encoding are the slow part of a build, and cameras are independent). Returns per episode its video columns
    and image statistics, and the frame shape."""
    import h5py

    video = _VideoFiles(root, f"observation.images.{camera}", fps)
    columns, parts, shape = [], [], ()
    try:
        for path in episodes:
            with h5py.File(path, "r") as f:
                frames = f[f"observations/images/{camera}"]
                shape = tuple(frames.shape[1:])
                cols, samples = video.append(frames)
            columns.append(cols)
            parts.append(image_stats(samples))
    finally:
        video.close()
    return columns, parts, shape


def write_lerobot(root: Path, episodes: Sequence[Path], *, fps: int) -> dict[str, Any]:
    """Build the LeRobot v3.0 dataset of `episodes` (HDF5 files, in order) at `root`; returns its info."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    if not episodes:
        raise ValueError("a LeRobot dataset needs at least one episode")
    tmp = root.with_name(root.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    first = read_episode(episodes[0], images=False)
    attrs = first["attrs"]
    cameras = [str(c) for c in attrs["cameras"]]
    numeric = _numeric_features(str(attrs["embodiment"]), str(attrs["action_mode"]), first["action"].shape[1])
    tasks: dict[str, int] = {}
    rows: list[dict[str, Any]] = []
    columns: dict[str, list[np.ndarray]] = {k: [] for k in numeric}
    data_chunk, data_file, data_bytes, writer, total = 0, 0, 0, None, 0
    pool = ProcessPoolExecutor(max(1, len(cameras)), mp_context=multiprocessing.get_context("spawn"))
    encoded = {c: pool.submit(_encode_camera, tmp, c, list(episodes), fps) for c in cameras}
    try:
        for index, path in enumerate(episodes):
            episode = read_episode(path, images=False)
            attrs, steps = episode["attrs"], len(episode["action"])
            task_index = tasks.setdefault(str(attrs["instruction"]), len(tasks))
            values = _episode_columns(episode)
            table = pa.table({
                **{k: _fixed_lists(v) for k, v in values.items()},
                "timestamp": pa.array(np.arange(steps, dtype=np.float32) / fps),
                "frame_index": pa.array(np.arange(steps, dtype=np.int64)),
                "episode_index": pa.array(np.full(steps, index, np.int64)),
                "index": pa.array(np.arange(total, total + steps, dtype=np.int64)),
                "task_index": pa.array(np.full(steps, task_index, np.int64)),
            })
            if writer is not None and data_bytes > DATA_FILES_SIZE_IN_MB * 2**20:
                writer.close()
                writer, data_bytes = None, 0
                data_chunk, data_file = _next_file(data_chunk, data_file)
            if writer is None:
                data_path = tmp / DATA_PATH.format(chunk_index=data_chunk, file_index=data_file)
                data_path.parent.mkdir(parents=True, exist_ok=True)
                writer = pq.ParquetWriter(data_path, table.schema)
            writer.write_table(table)
            data_bytes += table.nbytes
            row: dict[str, Any] = {
                "episode_index": index, "tasks": [str(attrs["instruction"])], "length": steps,
                "data/chunk_index": data_chunk, "data/file_index": data_file,
                "dataset_from_index": total, "dataset_to_index": total + steps,
            }
            for key, value in values.items():
                columns[key].append(value)
                row.update({f"stats/{key}/{k}": v for k, v in numeric_stats(value).items()})
            row.update({"meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0,
                        "robodojo/seed": int(attrs["seed"]), "robodojo/plan_hash": str(attrs["plan_hash"]),
                        "robodojo/setting": str(attrs["setting"]), "robodojo/success": bool(attrs["success"])})
            rows.append(row)
            total += steps
        shapes, image_parts = {}, {}
        for camera, future in encoded.items():
            video_columns, image_parts[camera], shapes[camera] = future.result()
            for row, cols, part in zip(rows, video_columns, image_parts[camera], strict=True):
                row.update(cols)
                row.update({f"stats/observation.images.{camera}/{k}": v for k, v in part.items()})
    finally:
        if writer is not None:
            writer.close()
        pool.shutdown(cancel_futures=True)

    features: dict[str, Any] = dict(numeric)
    for camera in cameras:
        height, width, channels = shapes[camera]
        features[f"observation.images.{camera}"] = {
            "dtype": "video", "shape": [height, width, channels], "names": ["height", "width", "channels"],
            "info": {"video.height": height, "video.width": width, "video.codec": "h264",
                     "video.pix_fmt": "yuv420p", "video.is_depth_map": False, "video.fps": fps,
                     "video.channels": channels, "has_audio": False}}
    features["timestamp"] = {"dtype": "float32", "shape": [1], "names": None}
    for name in DEFAULT_FEATURES[1:]:
        features[name] = {"dtype": "int64", "shape": [1], "names": None}
    info = {
        "codebase_version": CODEBASE_VERSION, "robot_type": str(first["attrs"]["embodiment"]),
        "total_episodes": len(rows), "total_frames": total, "total_tasks": len(tasks), "chunks_size": CHUNKS_SIZE,
        "data_files_size_in_mb": DATA_FILES_SIZE_IN_MB, "video_files_size_in_mb": VIDEO_FILES_SIZE_IN_MB,
        "fps": fps, "splits": {"train": f"0:{len(rows)}"}, "data_path": DATA_PATH,
        "video_path": VIDEO_PATH if cameras else None, "features": features,
    }
    stats: dict[str, Any] = {k: numeric_stats(np.concatenate(v)) for k, v in columns.items()}
    stats.update({f"observation.images.{c}": aggregate_image_stats(p) for c, p in image_parts.items()})
    meta = tmp / "meta"
    episodes_path = tmp / EPISODES_PATH.format(chunk_index=0, file_index=0)
    episodes_path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(_episode_row_table(rows), episodes_path)
    pq.write_table(_tasks_table(list(tasks)), meta / "tasks.parquet")
    (meta / "stats.json").write_text(json.dumps(
        {k: {s: v.tolist() for s, v in st.items()} for k, st in stats.items()}, indent=4))
    (meta / "info.json").write_text(json.dumps(info, indent=4))
    if root.exists():
        shutil.rmtree(root)
    os.replace(tmp, root)
    return info
