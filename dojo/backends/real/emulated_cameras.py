"""The emulator's cameras: the robot's head and wrist cameras rendered from the emulated world as it is now.

Each call renders a snapshot of the real-time world (taken under its lock, rendered outside it, so the physics
thread never waits for a frame). A real camera sometimes delivers no new frame in time; with probability
`drop` per camera and call the previous frame is delivered again instead (`dropped` counts them).
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

from dojo.backends.mujoco.render import RendererCache
from dojo.backends.real.cameras import CameraSource
from dojo.backends.real.realtime_sim import RealTimeSim


class EmulatedCameras(CameraSource):
    """Frames of `cameras` from `sim`, at width x height, with `drop` probability of a repeated frame."""

    def __init__(self, sim: RealTimeSim, cameras: Sequence[str], width: int, height: int, depth: bool = False,
                 drop: float = 0.0, seed: int = 0) -> None:
        self.sim, self.cameras, self.depth, self.drop = sim, list(cameras), depth, drop
        self.names = tuple(cameras)
        self.dropped = 0
        self._renderers = RendererCache(width, height)
        self._rng = np.random.default_rng(seed)
        self._data: tuple[mujoco.MjModel, mujoco.MjData] | None = None
        self._last: dict[str, np.ndarray] = {}

    def frames(self) -> dict[str, np.ndarray]:
        """One frame per camera (`<camera>_depth` too when depth is on), the world as it is now."""
        model, qpos = self.sim.snapshot()
        if self._data is None or self._data[0] is not model:
            self._data = (model, mujoco.MjData(model))
        data = self._data[1]
        data.qpos[:] = qpos
        mujoco.mj_forward(model, data)
        fresh = self._renderers.render(model, data, self.cameras, self.depth)
        for camera in self.cameras:
            if camera in self._last and self.drop and self._rng.random() < self.drop:
                self.dropped += 1
                continue
            self._last.update({k: v for k, v in fresh.items() if k in (camera, f"{camera}_depth")})
        return dict(self._last)

    def close(self) -> None:
        self._renderers.close()
