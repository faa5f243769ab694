"""The emulated robot, assembled: the real-time world, the arms' controllers on their buses, the cameras.

`EmulatedRobot` is what `backend.driver=emulator` runs against: a robot whose configuration names the `piper`
driver (PiPER, PiPER X) gets PiPER controllers on two python-can buses (`virtual`, or `dojo_host` to reach them
from other processes; channel names unique to this instance, as the SDK keeps one interface per channel name per
process), and `driver()` is the same
`PiperDriver` hardware uses, pointed at those buses. A robot whose protocol the emulator does not speak (the
ARX X5, driver `arx_x5`) is driven at joint level (`JointLevelDriver`).
"""

from __future__ import annotations

import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import mujoco

from dojo.backends.real.driver import Driver
from dojo.backends.real.emulated_cameras import EmulatedCameras
from dojo.backends.real.realtime_sim import RealTimeSim
from dojo.backends.real.robot_config import RealRobotConfig

EMULATED_DRIVERS = ("piper", "arx_x5")
"""Robot drivers (robot configs' `driver`) the emulator stands in for."""


@dataclass(frozen=True)
class EmulatorParams:
    """Imperfections and rates of the emulated hardware."""

    encoder_noise: float = 0.0
    """Standard deviation (rad) of Gaussian noise on each reported joint angle."""
    command_delay: float = 0.0
    """Seconds between a command frame's arrival and its effect."""
    feedback_drop: float = 0.0
    """Probability that any one feedback frame is never sent."""
    camera_drop: float = 0.0
    """Probability that a camera frame is late (the previous one is delivered again)."""
    feedback_hz: float = 200.0
    """Rate of the arm's periodic feedback (the PiPER's is 200 Hz)."""
    rx_buffer: int = 512
    """Frames a reader's queue on a virtual channel holds before the oldest are dropped."""
    bus: str = "virtual"
    """python-can interface of the PiPER's buses: `virtual` (this process only) or `dojo_host` (shared with
    other processes of the machine, as the console's e-stop process needs: `host_can`)."""
    seed: int = 0


class EmulatedRobot:
    """One emulated robot of `config.robot` in `model` (a plan's scene or the robot-only world), running."""

    def __init__(self, model: mujoco.MjModel, robot: Mapping[str, Any], config: RealRobotConfig,
                 params: EmulatorParams = EmulatorParams(), qpos: Sequence[float] | None = None) -> None:
        if config.driver not in EMULATED_DRIVERS:
            raise ValueError(f"robot {config.robot!r}: no emulator for driver {config.driver!r} "
                             f"(emulated: {', '.join(EMULATED_DRIVERS)})")
        self.robot, self.params, self.config = dict(robot), params, config
        self.sim = RealTimeSim(model, robot, config.joint_velocity, qpos)
        self.channels: tuple[str, ...] = ()
        self.controllers: Any = None
        if config.driver == "piper":
            from dojo.backends.real.piper_emulator import PiperCanEmulator

            self.channels = tuple(f"dojo-emulator-{uuid.uuid4().hex[:8]}-{side}" for side in ("left", "right"))
            self.controllers = PiperCanEmulator(self.sim, self.channels, interface=params.bus, params=params)
        self.sim.start()

    def driver(self) -> Driver:
        """A driver for this robot (not yet connected): as on hardware but on the emulator's buses, or at joint
        level for a protocol the emulator does not speak."""
        if self.config.driver == "piper":
            from dojo.backends.real.piper_driver import PiperDriver

            return PiperDriver(self.robot, self.channels, interface=self.params.bus)
        from dojo.backends.real.joint_level_driver import JointLevelDriver

        return JointLevelDriver(self.sim, self.robot, self.params.encoder_noise, self.params.seed)

    def cameras(self, names: Sequence[str], width: int, height: int, depth: bool = False) -> EmulatedCameras:
        return EmulatedCameras(self.sim, names, width, height, depth, self.params.camera_drop, self.params.seed)

    def close(self) -> None:
        self.sim.stop()
        if self.controllers is not None:
            self.controllers.close()
