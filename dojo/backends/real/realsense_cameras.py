"""An Intel RealSense camera's colour stream through the maker's `pyrealsense2`, e.g. the head camera at 640x480.

The device is chosen by serial number (`realsense:123456789`), or is the one connected (`realsense`). Opening
looks the devices up first (`rs.context().query_devices()`), so a camera that is not there is reported by name
and serial with the serials that are, instead of failing inside the pipeline. The stream is RGB8 at width x
height, 30 fps; a read takes the newest frameset without waiting (`poll_for_frames`), repeating the previous
frame when none is new.
"""

from __future__ import annotations

import numpy as np

from dojo.backends.real.cameras import CameraError, CameraSource, StallGuard

FPS = 30
FIRST_FRAME_TIMEOUT_MS = 5000
STALL_READS = 100
"""Reads in a row without a new frame after which the camera is reported dead (4 s of a 25 Hz control loop)."""


class RealSenseCamera(CameraSource):
    """Camera `name` on the RealSense with serial `serial` ("" : the only one connected)."""

    def __init__(self, name: str, serial: str, width: int, height: int) -> None:
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
        self._pipeline = rs.pipeline(context)
        try:
            self._pipeline.start(config)
            first = self._pipeline.wait_for_frames(FIRST_FRAME_TIMEOUT_MS)
        except RuntimeError as exc:
            raise CameraError(f"{what}: cannot stream RGB {width}x{height} at {FPS} fps: {exc}") from exc
        self._last = self._color(first)
        self._stall = StallGuard(what, STALL_READS)

    def frames(self) -> dict[str, np.ndarray]:
        frameset = self._pipeline.poll_for_frames()
        if frameset:
            self._last = self._color(frameset)
            self._stall.delivered()
        else:
            self._stall.missed()
            self.dropped += 1
        return {self.names[0]: self._last}

    @staticmethod
    def _color(frameset: object) -> np.ndarray:
        return np.asanyarray(frameset.get_color_frame().get_data()).copy()  # type: ignore[attr-defined]

    def close(self) -> None:
        self._pipeline.stop()
