"""The real backend: robot drivers behind one interface, a safety layer, and a hardware emulator.

`driver.Driver` is the interface (PiPER / PiPER X through `piper-sdk` in `piper_driver`), `cameras.CameraSource`
the cameras' (OpenCV/V4L2, RealSense, or the emulator's); `safety` sits between
the policy and the driver; `realtime_sim` + `piper_emulator` are the emulated hardware that the unmodified
maker's SDK drives over a python-can bus, so all of it runs and is tested without a robot. The makers' packages
and python-can are the optional extra `robodojo[real]` (`piper_emulator` needs python-can, `piper_driver`
imports piper-sdk when it connects); the rest needs only the base install.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from dojo.backends.real.backend import RealBackend


def make(options: Any) -> RealBackend:
    """The backend registry's constructor (`make(options)`, options as `dojo.backends.registry.BackendOptions`):
    cameras, width, height and depth from the options; from the `backend=real` config's own keys (`settings`):
    `driver` (emulator | piper), `can` (the left and right arm's CAN buses), `emulator` (EmulatorParams fields),
    `cameras` (each camera's source: `emulator`, or a map camera -> opencv:DEVICE | realsense:SERIAL).
    A robot has no simulator state to give, so a privileged policy (the oracle) cannot run on it."""
    from dojo.backends.real.backend import RealBackend

    if getattr(options, "privileged", False):
        raise ValueError("backend real: a privileged policy (the oracle) reads the simulator's state, which a "
                         "robot does not have; evaluate a policy that reads observations")
    settings = dict(options.settings)
    return RealBackend(driver=str(settings.get("driver", "emulator")), can=settings.get("can"),
                       cameras=options.cameras, width=options.width, height=options.height, depth=options.depth,
                       emulator=settings.get("emulator"), sources=settings.get("cameras", "emulator"))


SIMULATED_ONLY = {
    "actors": "a robot's world has no scripted actors: evaluate this task in simulation",
    "events": "a robot's world has no scripted events: evaluate this task in simulation",
}


def unsupported(features: Sequence[str], settings: Mapping[str, Any]) -> dict[str, str]:
    """What only a simulator can do: act by script. A robot's physics is the world's own, so contacts,
    constraints and deformable objects are not a question."""
    return {f: SIMULATED_ONLY[f] for f in features if f in SIMULATED_ONLY}
