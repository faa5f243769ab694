"""A real robot's settings beyond its robot spec: driver, buses, joint speed limits, safety workspace.

The robot spec (specs/robots) describes the robot for the compiler and is the same in simulation and on
hardware; what only hardware needs lives beside the real backend, one YAML file per robot id in `robots/`.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources

import numpy as np
import yaml


@dataclass(frozen=True)
class RealRobotConfig:
    """The contents of `robots/<robot id>.yaml` (see piper_bimanual.yaml for every field's meaning)."""

    robot: str
    driver: str
    can: tuple[str, ...]
    joint_velocity: np.ndarray
    joint_acceleration: np.ndarray
    max_jump: float
    workspace_lo: np.ndarray
    workspace_hi: np.ndarray
    table_z: float
    table_penetration: float
    arm_clearance: float
    watchdog_s: float
    estop_hold_s: float
    return_speed: float

    @classmethod
    def load(cls, robot_id: str) -> RealRobotConfig:
        """The built-in configuration of `robot_id`; a robot without one cannot run on the real backend."""
        path = resources.files("dojo.backends.real") / "robots" / f"{robot_id}.yaml"
        if not path.is_file():
            known = sorted(p.name.removesuffix(".yaml") for p in (resources.files("dojo.backends.real") / "robots")
                           .iterdir() if p.name.endswith(".yaml"))
            raise ValueError(f"robot {robot_id!r} has no real-robot configuration; configured: {known}")
        data = yaml.safe_load(path.read_text())
        safety = data["safety"]
        return cls(
            robot=data["robot"], driver=data["driver"], can=tuple(data.get("can", ())),
            joint_velocity=np.asarray(data["joint_velocity"], dtype=float),
            joint_acceleration=np.asarray(data["joint_acceleration"], dtype=float),
            max_jump=float(safety["max_jump"]),
            workspace_lo=np.asarray(safety["workspace"]["lo"], dtype=float),
            workspace_hi=np.asarray(safety["workspace"]["hi"], dtype=float),
            table_z=float(safety["table_z"]), table_penetration=float(safety["table_penetration"]),
            arm_clearance=float(safety["arm_clearance"]),
            watchdog_s=float(safety["watchdog_ms"]) / 1000.0, estop_hold_s=float(safety["estop_hold_s"]),
            return_speed=float(safety["return_speed"]),
        )
