"""The bimanual embodiments as plain data, so shapes and limits can be checked without a simulator.

Joint action/state layout (D = 14): ``[left j1..j6, left gripper, right j1..j6, right gripper]``, joints in
radians, grippers normalised to 0 (closed) .. 1 (open). End-effector layout (D = 16), per arm:
``[x, y, z, qw, qx, qy, qz, gripper]`` in the arm's base frame, metres.

The joint limits are APPROXIMATE, taken from the makers' public specifications (ARX X5 product sheet and SDK
URDF; AgileX Piper user manual and URDF; Piper X assumed to share Piper's ranges). They are a sanity bound
for the checker and the random policy, not a calibration; the robot specs in ``specs/robots`` are the
authority for simulation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ACTION_MODES = ("joint", "ee")
CAMERAS = ("head", "left_wrist", "right_wrist")
ARMS = ("left", "right")
EE_PER_ARM = 8


@dataclass(frozen=True)
class Embodiment:
    """One bimanual robot: two identical arms with a parallel gripper each."""

    name: str
    arm_joint_limits: tuple[tuple[float, float], ...]  # per joint of one arm, radians
    home: tuple[float, ...]  # a comfortable joint pose of one arm, radians, inside the limits
    reach_m: float  # a generous bound on |ee position| in the arm's base frame
    control_hz: float = 50.0

    @property
    def joints_per_arm(self) -> int:
        return len(self.arm_joint_limits)

    def action_dim(self, mode: str) -> int:
        """Width D of an action chunk in ``mode``."""
        if mode == "joint":
            return 2 * (self.joints_per_arm + 1)
        if mode == "ee":
            return 2 * EE_PER_ARM
        raise ValueError(f"unknown action mode {mode!r}; choose one of {ACTION_MODES}")

    def gripper_indices(self) -> tuple[int, int]:
        """Where the two grippers sit in the joint layout."""
        return self.joints_per_arm, 2 * self.joints_per_arm + 1

    def joint_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds of the full 14-wide joint vector (grippers 0..1)."""
        arm = [*self.arm_joint_limits, (0.0, 1.0)]
        lo = np.array([b[0] for b in arm] * 2, dtype=np.float32)
        hi = np.array([b[1] for b in arm] * 2, dtype=np.float32)
        return lo, hi

    def home_joint_pos(self) -> np.ndarray:
        """The 14-wide home pose with open grippers."""
        return np.array([*self.home, 1.0] * 2, dtype=np.float32)


EMBODIMENTS: dict[str, Embodiment] = {
    "arx_x5_bimanual": Embodiment(
        name="arx_x5_bimanual",
        arm_joint_limits=((-3.14, 2.62), (0.0, 3.14), (0.0, 3.14), (-1.57, 1.57), (-1.57, 1.57), (-2.09, 2.09)),
        home=(0.0, 0.8, 0.8, 0.0, 0.0, 0.0),
        reach_m=1.0,
    ),
    "piper_bimanual": Embodiment(
        name="piper_bimanual",
        arm_joint_limits=((-2.62, 2.62), (0.0, 3.14), (-2.97, 0.0), (-1.75, 1.75), (-1.22, 1.22), (-2.09, 2.09)),
        home=(0.0, 0.8, -0.8, 0.0, 0.0, 0.0),
        reach_m=1.0,
    ),
    "piperx_bimanual": Embodiment(
        name="piperx_bimanual",
        arm_joint_limits=((-2.62, 2.62), (0.0, 3.14), (-2.97, 0.0), (-1.75, 1.75), (-1.22, 1.22), (-2.09, 2.09)),
        home=(0.0, 0.8, -0.8, 0.0, 0.0, 0.0),
        reach_m=1.0,
    ),
}


def get_embodiment(name: str) -> Embodiment:
    """Look an embodiment up by name, naming the valid ones on a miss."""
    try:
        return EMBODIMENTS[name]
    except KeyError:
        raise ValueError(f"unknown embodiment {name!r}; choose one of {sorted(EMBODIMENTS)}") from None
