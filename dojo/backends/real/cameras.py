"""The robot's cameras behind one interface, and where each camera's frames come from (`backend.cameras`).

A `CameraSource` delivers the newest frame of each camera it serves (RGB uint8, height x width x 3) when asked,
never blocking on a late camera: a camera with no new frame in time delivers its previous one again and counts
it in `dropped`, as the emulator's cameras do. Sources: the emulator's rendered cameras (`EmulatedCameras`), a
USB camera through OpenCV/V4L2 (`opencv_cameras`, which also reads video files), an Intel RealSense
(`realsense_cameras`, colour and aligned depth). The makers' packages (opencv-python-headless, pyrealsense2) are
the `real` extra and are imported only when a camera of theirs is opened.

`backend.cameras` chooses per camera: `emulator` (the default: every camera rendered by the emulator, which only
`backend.driver=emulator` has), or a map from camera name to `opencv:<index or device path or file>`,
`realsense:<serial>` (`realsense` alone: the one connected), or `emulator`, e.g.
`backend.cameras={head:realsense:123456789,left_wrist:opencv:/dev/video2,right_wrist:opencv:/dev/video4}`.
A camera the map does not name is emulated; on hardware every camera filmed must be named.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

EMULATOR = "emulator"
KINDS = ("opencv", "realsense", EMULATOR)


class CameraError(RuntimeError):
    """A camera that cannot be opened or stopped delivering (the message names the camera and its device)."""


class CameraSource(ABC):
    """Frames of the cameras in `names`."""

    names: tuple[str, ...]
    dropped: int

    @abstractmethod
    def frames(self) -> dict[str, np.ndarray]:
        """The newest frame of every camera served, by name (`<name>_depth` too where depth is served)."""

    def close(self) -> None:
        """Release the device(s)."""


class StallGuard:
    """Counts a camera's consecutive misses: a repeated frame is a drop, `limit` in a row is a dead camera."""

    def __init__(self, what: str, limit: int) -> None:
        self.what, self.limit, self.misses = what, limit, 0

    def missed(self) -> None:
        self.misses += 1
        if self.misses >= self.limit:
            raise CameraError(f"{self.what} delivered no new frame in {self.limit} reads in a row "
                              "(unplugged, or the stream ended)")

    def delivered(self) -> None:
        self.misses = 0


class CameraSet(CameraSource):
    """Several sources as one (the cameras of a robot may come from different makers)."""

    def __init__(self, sources: Sequence[CameraSource]) -> None:
        self.sources = list(sources)
        self.names = tuple(n for s in self.sources for n in s.names)

    @property
    def dropped(self) -> int:  # type: ignore[override]
        return sum(s.dropped for s in self.sources)

    def frames(self) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {}
        for source in self.sources:
            out.update(source.frames())
        return out

    def close(self) -> None:
        for source in self.sources:
            source.close()


def parse_sources(setting: Any, names: Sequence[str]) -> dict[str, tuple[str, str]]:
    """Each camera of `names` with its source (kind, device) from the `backend.cameras` setting (see the module
    docstring); a bad setting raises ValueError naming the key. The map may name cameras this run does not
    film (a lab's configuration names all its cameras; a policy may watch fewer)."""
    if setting is None or setting == EMULATOR:
        return {name: (EMULATOR, "") for name in names}
    if not isinstance(setting, Mapping):
        raise ValueError(f"backend.cameras: expected 'emulator' or a map camera -> source, got {setting!r}")
    out = {}
    for name in names:
        kind, _, device = str(setting.get(name, EMULATOR)).partition(":")
        if kind not in KINDS or (kind == "opencv" and not device):
            raise ValueError(f"backend.cameras.{name}: {setting.get(name)!r} is not a camera source; use "
                             "opencv:<index or device path or video file>, realsense:<serial> (or realsense), "
                             "or emulator")
        out[name] = (kind, device)
    return out


def open_cameras(sources: Mapping[str, tuple[str, str]], width: int, height: int, depth: bool,
                 emulated: Callable[[Sequence[str]], CameraSource] | None) -> CameraSource:
    """Open every camera of `sources` (from `parse_sources`) at width x height. `emulated(names)` opens the
    emulator's cameras (None on hardware: a camera left to the emulator is then an error)."""
    from dojo.backends.real.opencv_cameras import OpenCVCamera
    from dojo.backends.real.realsense_cameras import RealSenseCamera

    colour_only = [n for n, (kind, _) in sources.items() if kind == "opencv"]
    if depth and colour_only:
        raise CameraError(f"cameras {colour_only}: USB cameras (opencv) give RGB only; depth comes from the "
                          "emulator or a RealSense (realsense:<serial>)")
    emulated_names = [n for n, (kind, _) in sources.items() if kind == EMULATOR]
    if emulated_names and emulated is None:
        raise CameraError(f"cameras {emulated_names} have no hardware source: name each in backend.cameras, e.g. "
                          f"backend.cameras={{{emulated_names[0]}:opencv:/dev/video0}}")
    opened: list[CameraSource] = []
    try:
        if emulated_names:
            opened.append(emulated(emulated_names))  # type: ignore[misc]
        for name, (kind, device) in sources.items():
            if kind == "opencv":
                opened.append(OpenCVCamera(name, device, width, height))
            elif kind == "realsense":
                opened.append(RealSenseCamera(name, device, width, height, depth))
    except BaseException:
        for source in opened:
            source.close()
        raise
    return CameraSet(opened)
