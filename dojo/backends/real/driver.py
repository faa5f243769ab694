"""The one interface every robot driver implements: read the arms, command joints, hold, home, stop.

A driver speaks to one bimanual robot (two arms of J joints and a parallel gripper each, left first) through the
maker's own package, or to the emulator through the same package. It is deliberately small and joint-level:
end-effector actions are turned into joint targets by the backend's IK on the robot's MuJoCo model (the same
IK as in simulation), and the safety layer checks every joint target against limits and the robot's collision
model before a driver sees it. A driver therefore never decides what is safe; it moves, reports, and stops.

Units everywhere: radians, radians per second, grippers normalised 0 (closed) .. 1 (open at the robot's
`gripper_max_width`), arrays with the arm on the first axis.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from collections.abc import Mapping
from typing import Any, Self

import numpy as np


def home_of(robot: Mapping[str, Any]) -> tuple[tuple[np.ndarray, np.ndarray], float]:
    """The reset pose of a robot from the compiler's robot handles: (arm joints [2, J], grippers [2] 0..1), and
    its gripper's full width in metres (what 1 is)."""
    ctrl = np.asarray(robot["home_ctrl"], dtype=float).reshape(2, -1)
    max_width = float(robot["gripper_max_width"])
    return (ctrl[:, :-1], ctrl[:, -1] / max_width), max_width


@dataclass(frozen=True)
class RobotState:
    """What the arms report: joint positions and velocities [2, J], grippers [2] (0..1), and `stamp`, the
    driver's time (seconds, its own clock) of the newest feedback the values come from."""

    joint_pos: np.ndarray
    joint_vel: np.ndarray
    gripper: np.ndarray
    stamp: float


class Driver(ABC):
    """One bimanual robot. `connect()` before use (enables the motors and waits for the first feedback);
    `close()` (or leaving a `with` block) disconnects without moving the arms."""

    @property
    @abstractmethod
    def home_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The reset pose: arm joints [2, J] and grippers [2], from the robot spec's `home`."""

    @abstractmethod
    def connect(self) -> None:
        """Open the connection, enable the motors and wait until the arms report their state."""

    @abstractmethod
    def read(self) -> RobotState:
        """The newest state the arms reported (never blocks on the hardware)."""

    @abstractmethod
    def command(self, joint_pos: np.ndarray, gripper: np.ndarray, speed: float = 1.0) -> None:
        """Send joint targets [2, J] and grippers [2]. The arms move there at no more than `speed` (0..1] times
        their maximum joint speeds; the controller interpolates, so one command is enough to get there."""

    @abstractmethod
    def estop(self) -> None:
        """The hardware's own emergency stop. Last resort: on most arms it needs an operator to recover, so the
        safety layer's e-stop holds and returns slowly through `command` instead."""

    def hold(self) -> None:
        """Stop where the arms are now: command the measured joints and grippers."""
        state = self.read()
        self.command(state.joint_pos, state.gripper)

    def home(self, speed: float) -> None:
        """Move to the reset pose at `speed` times the maximum joint speeds (returns at once)."""
        joint_pos, gripper = self.home_pose
        self.command(joint_pos, gripper, speed)

    def close(self) -> None:
        """Disconnect (the arms keep their last target)."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
