"""The emulated PiPER rig for the real-robot tests, and the figures they measure.

A rig is the emulated bimanual PiPER (`EmulatedRobot`) in the compiler's robot-only world: the world stepped in
real time and the CAN emulator answering on two python-can virtual buses, for `PiperDriver` on the unmodified
`piper-sdk` to connect to. Channel names are unique per rig, because the SDK keeps one interface object per
channel name for the whole process.

Timings are measured, never asserted: each test adds its figures with `figures.add(name, value)`; they are
printed at the end of the run and written to `<results root>/figures/real_emulator.json`.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import mujoco
import pytest
from dojo.backends.real.emulator import EmulatedRobot, EmulatorParams
from dojo.backends.real.realtime_sim import RealTimeSim
from dojo.backends.real.robot_config import RealRobotConfig
from dojo.compiler.robot_emit import build_robot_world
from dojo.compiler.spec_library import SpecLibrary
from dojo.evaluation.run_dir import results_root

if TYPE_CHECKING:  # python-can (the `real` extra) is needed only by the tests that start an emulator
    from dojo.backends.real.piper_emulator import PiperCanEmulator

ROBOT_ID = "piper_bimanual"
_FIGURES: dict[str, Any] = {}


class Figures:
    """Measured values of this run, by name."""

    def add(self, name: str, value: Any) -> None:
        _FIGURES[name] = value


@pytest.fixture(scope="session")
def figures() -> Figures:
    return Figures()


def pytest_terminal_summary(terminalreporter: Any) -> None:
    if not _FIGURES:
        return
    path = results_root() / "figures" / "real_emulator.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(_FIGURES, indent=1, sort_keys=True) + "\n")
    terminalreporter.section("real-robot emulator figures")
    for name, value in sorted(_FIGURES.items()):
        terminalreporter.write_line(f"{name}: {value}")
    terminalreporter.write_line(f"(written to {path})")


@pytest.fixture(scope="session")
def piper_world() -> tuple[mujoco.MjModel, dict[str, Any], RealRobotConfig]:
    """The robot-only world of the bimanual PiPER, its handles and its real-robot configuration."""
    spec = SpecLibrary.load(strict=False).get("robot", ROBOT_ID).data
    world, handles = build_robot_world(spec)
    return world.compile(), asdict(handles), RealRobotConfig.load(ROBOT_ID)


@dataclass
class Rig:
    emulated: EmulatedRobot
    config: RealRobotConfig
    model: mujoco.MjModel

    @property
    def sim(self) -> RealTimeSim:
        return self.emulated.sim

    @property
    def emulator(self) -> PiperCanEmulator:
        return self.emulated.controllers

    @property
    def channels(self) -> tuple[str, ...]:
        return self.emulated.channels

    @property
    def robot(self) -> dict[str, Any]:
        return self.emulated.robot


@pytest.fixture
def make_rig(piper_world) -> Iterator[Callable[..., Rig]]:
    """Start an emulated rig with the given `EmulatorParams` fields (the driver is the test's to connect)."""
    model, robot, config = piper_world
    started: list[Rig] = []

    def make(**params: Any) -> Rig:
        pytest.importorskip("can")
        rig = Rig(EmulatedRobot(model, robot, config, EmulatorParams(**params)), config, model)
        started.append(rig)
        return rig

    yield make
    for rig in started:
        rig.emulated.close()
