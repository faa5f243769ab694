"""Correctly shaped synthetic observations (DESIGN section 4), for the checker, the bench and tests.

They follow the observation contract exactly, so a policy that survives them will at least not fail on
shapes and dtypes when it meets the simulator.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from xpolicylab.embodiments import CAMERAS, Embodiment


def noise_images(cameras: Sequence[str], width: int, height: int, seed: int = 0) -> dict[str, np.ndarray]:
    """One uint8[H, W, 3] noise image per camera (noise, so no codec can cheat by compressing it)."""
    rng = np.random.default_rng(seed)
    return {cam: rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8) for cam in cameras}


def synthetic_observation(
    embodiment: Embodiment,
    cameras: Sequence[str] = CAMERAS,
    width: int = 640,
    height: int = 480,
    *,
    depth: bool = False,
    step: int = 0,
    episode: int = 0,
    task: str = "xpolicylab_check",
    seed: int = 0,
    images: dict[str, np.ndarray] | None = None,
) -> dict[str, Any]:
    """One environment's observation; the joint pose is the home pose plus a small seeded perturbation."""
    rng = np.random.default_rng(seed + 7919 * step)
    lo, hi = embodiment.joint_bounds()
    joint_pos = np.clip(embodiment.home_joint_pos() + rng.uniform(-0.05, 0.05, lo.shape).astype(np.float32), lo, hi)
    grippers = list(embodiment.gripper_indices())
    joint_pos[grippers] = rng.uniform(0.2, 1.0, 2)
    ee_pose = np.array([[0.3, 0.0, 0.25, 1.0, 0.0, 0.0, 0.0]] * 2, dtype=np.float32)
    ee_pose[:, :3] += rng.uniform(-0.02, 0.02, (2, 3)).astype(np.float32)
    obs: dict[str, Any] = {
        "instruction": "hold still",
        "images": images if images is not None else noise_images(cameras, width, height, seed),
        "state": {
            "joint_pos": joint_pos.astype(np.float32),
            "joint_vel": np.zeros_like(joint_pos),
            "ee_pose": ee_pose,
            "gripper": joint_pos[grippers].astype(np.float32),
        },
        "meta": {"task": task, "episode": episode, "step": step, "embodiment": embodiment.name,
                 "control_hz": embodiment.control_hz},
    }
    if depth:
        obs["depth"] = {cam: np.full((height, width), 800, dtype=np.uint16) for cam in cameras}
    return obs


def synthetic_batch(embodiment: Embodiment, n: int, cameras: Sequence[str] = CAMERAS, width: int = 640,
                    height: int = 480, *, step: int = 0, seed: int = 0, stacked: bool = False) -> list[dict[str, Any]]:
    """``n`` observations with distinct states. The noise images are shared to keep memory bounded, or with
    ``stacked`` each environment's are rows of one array per camera, as a batched simulator renders them (the
    same noise in every row)."""
    images = noise_images(cameras, width, height, seed)
    batches = {cam: np.repeat(image[None], n, axis=0) for cam, image in images.items()} if stacked else None
    return [synthetic_observation(embodiment, cameras, width, height, step=step, episode=i, seed=seed + i,
                                  images={cam: b[i] for cam, b in batches.items()} if batches else images)
            for i in range(n)]
