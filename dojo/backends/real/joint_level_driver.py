"""A driver straight onto the emulator's joint controllers, for a robot whose bus protocol it does not speak.

The PiPER and PiPER X are emulated down to their CAN protocol, so the maker's SDK drives the emulator as it
drives the arms. The ARX X5's protocol is inside ARX's closed library (see robots/arx_x5_bimanual.yaml), so its
emulated arms are driven here at the level the `Driver` interface itself works at: joint targets reached at a
fraction of the maximum joint speeds by the firmware-like controllers of `RealTimeSim`, gripper widths, the
measured state with the emulator's encoder noise. Everything above the driver (safety layer, backend, console)
is the same for every robot.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from dojo.backends.real.driver import Driver, RobotState, home_of
from dojo.backends.real.realtime_sim import RealTimeSim


class JointLevelDriver(Driver):
    """Both arms of the emulated robot in `sim`; `encoder_noise` (rad, standard deviation) on reported joints."""

    def __init__(self, sim: RealTimeSim, robot: Mapping[str, Any], encoder_noise: float = 0.0,
                 seed: int = 0) -> None:
        self.sim, self.encoder_noise = sim, encoder_noise
        self._home, self.max_width = home_of(robot)
        self._rng = np.random.default_rng(seed)

    @property
    def home_pose(self) -> tuple[np.ndarray, np.ndarray]:
        return self._home[0].copy(), self._home[1].copy()

    def connect(self) -> None:
        """The emulated arms are enabled and report from the start: nothing to open."""

    def read(self) -> RobotState:
        with self.sim.lock:
            readings = [self.sim.reading(arm) for arm in (0, 1)]
        pos = np.stack([r.joint_pos for r in readings])
        if self.encoder_noise:
            pos = pos + self._rng.normal(0.0, self.encoder_noise, pos.shape)
        return RobotState(joint_pos=pos, joint_vel=np.stack([r.joint_vel for r in readings]),
                          gripper=np.clip([r.width / self.max_width for r in readings], 0.0, 1.0),
                          stamp=self.sim.clock())

    def command(self, joint_pos: np.ndarray, gripper: np.ndarray, speed: float = 1.0) -> None:
        targets = np.asarray(joint_pos, dtype=float).reshape(2, -1)
        widths = np.clip(np.asarray(gripper, dtype=float).reshape(2), 0.0, 1.0) * self.max_width
        with self.sim.lock:
            for arm in (0, 1):
                self.sim.set_joint_target(arm, targets[arm], speed)
                self.sim.set_gripper_target(arm, float(widths[arm]))

    def estop(self) -> None:
        with self.sim.lock:
            for arm in (0, 1):
                self.sim.hold_arm(arm)
