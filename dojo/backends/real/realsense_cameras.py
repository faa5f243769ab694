"""An Intel RealSense camera through the maker's `pyrealsense2`: colour, and depth aligned to it, e.g. the head
camera at 640x480.

The device is chosen by serial number (`realsense:123456789`), or is the one connected (`realsense`). Opening
looks the devices up first (`rs.context().query_devices()`), so a camera that is not there is reported by name
and serial with the serials that are, instead of failing inside the pipeline. The stream is RGB8 at width x
height, 30 fps; a read takes the newest frameset without waiting (`poll_for_frames`), repeating the previous
frame when none is new.

With depth (`backend.depth=true`), the Z16 depth stream runs at the same size and rate, is aligned to the colour
image by the SDK (`rs.align`: depth pixel (u, v) lies behind colour pixel (u, v)) and is delivered as
`<camera>_depth`, uint16 millimetres along the optical axis: the convention of the simulator's rendered depth
(`dojo.backends.mujoco.render`), so a policy sees the same units from both. The raw units are the device's depth
scale (1 mm on most D400 cameras, 0.1 mm on the D405); 0 is the camera's "no depth here" (shadows, out of range).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dojo.backends.real.cameras import CameraError, CameraSource, StallGuard

FPS = 30
FIRST_FRAME_TIMEOUT_MS = 5000
STALL_READS = 100
"""Reads in a row without a new frame after which the camera is reported dead (4 s of a 25 Hz control loop)."""


class RealSenseCamera(CameraSource):
    """Camera `name` on the RealSense with serial `serial` ("" : the only one connected)."""

    def __init__(self, name: str, serial: str, width: int, height: int, depth: bool = False) -> None:
        import pyrealsense2 as rs

        self.names, self.dropped = (name,), 0
        context = rs.context()
        connected = [d.get_info(rs.camera_info.serial_number) for d in context.query_devices()]
        what = f"camera {name!r} (RealSense {'serial ' + repr(serial) if serial else 'device'})"
        if (serial and serial not in connected) or (not serial and len(connected) != 1):
            raise CameraError(f"{what}: not found; RealSense devices connected: {', '.join(connected) or 'none'}"
                              + ("" if serial or not connected else " (name one: realsense:<serial>)"))
        config = rs.config()
        config.enable_device(serial or connected[0])
        config.enable_stream(rs.stream.color, width, height, rs.format.rgb8, FPS)
        if depth:
            config.enable_stream(rs.stream.depth, width, height, rs.format.z16, FPS)
        self._pipeline = rs.pipeline(context)
        try:
            profile = self._pipeline.start(config)
            self._depth = DepthToColour(profile.get_device().first_depth_sensor().get_depth_scale()) \
                if depth else None
            first = self._pipeline.wait_for_frames(FIRST_FRAME_TIMEOUT_MS)
        except RuntimeError as exc:
            streams = "RGB" + (" and depth" if depth else "")
            raise CameraError(f"{what}: cannot stream {streams} {width}x{height} at {FPS} fps: {exc}") from exc
        self._last = camera_frames(name, first, self._depth)
        self._stall = StallGuard(what, STALL_READS)

    def frames(self) -> dict[str, np.ndarray]:
        frameset = self._pipeline.poll_for_frames()
        if frameset:
            self._last = camera_frames(self.names[0], frameset, self._depth)
            self._stall.delivered()
        else:
            self._stall.missed()
            self.dropped += 1
        return dict(self._last)

    def close(self) -> None:
        self._pipeline.stop()


class DepthToColour:
    """Aligns a frameset's depth to its colour image and converts it to millimetres (see the module docstring);
    `depth_scale`: metres per raw unit, the device's."""

    def __init__(self, depth_scale: float) -> None:
        import pyrealsense2 as rs

        self.depth_scale = float(depth_scale)
        self._align = rs.align(rs.stream.color)

    def __call__(self, frameset: Any) -> tuple[Any, np.ndarray]:
        """The aligned frameset and its depth image, uint16 millimetres."""
        aligned = self._align.process(frameset)
        raw = np.asanyarray(aligned.get_depth_frame().get_data())
        return aligned, depth_millimetres(raw, self.depth_scale)


def camera_frames(name: str, frameset: Any, depth: DepthToColour | None) -> dict[str, np.ndarray]:
    """`name`'s colour image from a frameset, and with `depth` its aligned depth as `<name>_depth`."""
    out = {}
    if depth is not None:
        frameset, out[f"{name}_depth"] = depth(frameset)
    out[name] = np.asanyarray(frameset.get_color_frame().get_data()).copy()
    return out


def depth_millimetres(raw: np.ndarray, depth_scale: float) -> np.ndarray:
    """Raw Z16 depth (units of `depth_scale` metres) as uint16 millimetres, 0 kept as "no depth"."""
    millimetres = np.rint(raw.astype(np.float64) * (depth_scale * 1000.0))
    return np.clip(millimetres, 0, 65535).astype(np.uint16)
