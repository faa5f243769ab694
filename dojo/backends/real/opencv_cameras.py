"""A USB camera through OpenCV (V4L2 on Linux), e.g. a wrist camera at 640x480.

The device is a V4L2 index (`2`) or device path (`/dev/video2`), opened with the V4L2 back-end, or any other
path OpenCV's `VideoCapture` opens (a video file: the same code path reads recorded footage, which is how it is
tested without a camera). The capture is asked for width x height and a one-frame buffer, so a read returns
the newest frame rather than one queued while the control loop was busy; frames of another size are resized.
OpenCV delivers BGR; frames here are RGB, as every other source's.
"""

from __future__ import annotations

import glob
import sys

import numpy as np

from dojo.backends.real.cameras import CameraError, CameraSource, StallGuard

STALL_READS = 30
"""Reads in a row without a frame after which the camera is reported dead (about a second at 30 fps)."""


class OpenCVCamera(CameraSource):
    """Camera `name` on OpenCV device `device` (index, device path or file), frames at width x height."""

    def __init__(self, name: str, device: str, width: int, height: int) -> None:
        import cv2

        self.names, self.width, self.height, self.dropped = (name,), width, height, 0
        self._what = f"camera {name!r} (OpenCV device {device!r})"
        v4l2 = device.isdigit() or device.startswith("/dev/video")
        source: int | str = int(device) if device.isdigit() else device
        self._capture = cv2.VideoCapture(source, cv2.CAP_V4L2 if v4l2 and sys.platform == "linux" else cv2.CAP_ANY)
        if not self._capture.isOpened():
            self._capture.release()
            present = ", ".join(sorted(glob.glob("/dev/video*"))) or "none"
            raise CameraError(f"{self._what}: cannot open it (V4L2 devices present: {present})")
        if v4l2:
            self._capture.set(cv2.CAP_PROP_FRAME_WIDTH, width)
            self._capture.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
            self._capture.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        self._stall = StallGuard(self._what, STALL_READS)
        self._last: np.ndarray | None = None
        while self._last is None:  # the first frame, so that every later read has one to repeat
            self._read()

    def frames(self) -> dict[str, np.ndarray]:
        self._read()
        return {self.names[0]: self._last}  # type: ignore[dict-item]

    def _read(self) -> None:
        import cv2

        ok, bgr = self._capture.read()
        if not ok or bgr is None:
            self._stall.missed()
            self.dropped += self._last is not None
            return
        self._stall.delivered()
        if bgr.shape[:2] != (self.height, self.width):
            bgr = cv2.resize(bgr, (self.width, self.height), interpolation=cv2.INTER_AREA)
        self._last = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def close(self) -> None:
        self._capture.release()
