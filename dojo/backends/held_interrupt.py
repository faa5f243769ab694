"""Ctrl-C held back while a backend's device work is under way, and delivered the moment it ends.

Why. A jitted tick of the mjx backend calls back into Python (MuJoCo Warp's kernels are launched from XLA through
Warp's FFI callbacks). A KeyboardInterrupt raised inside such a callback leaves XLA waiting for a buffer that is
never written; the run then prints `dojo run: interrupted`, its results stored, and hangs for good in the
interpreter's teardown, where JAX's CPU client joins the thread still waiting (`dojo run backend=mjx
backend.impl=warp`, SIGINT while stepping, 2-core CI machine, 2026-12-03: killed by hand after 54 minutes). Held
back to the end of the tick, the interrupt arrives between ticks, where the loop stops cleanly.
"""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from types import FrameType
from typing import Iterator


@contextmanager
def interrupts_held() -> Iterator[None]:
    """Run the block with SIGINT held back; once it ends normally, hand a SIGINT that came to the handler it would
    have gone to (Python's own raises KeyboardInterrupt there). Only the main thread receives signals in Python, so
    elsewhere, or where SIGINT has no Python handler (ignored, or the default action), the block runs as it is."""
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or not callable(previous):
        yield
        return
    came: list[FrameType | None] = []
    signal.signal(signal.SIGINT, lambda signum, frame: came.append(frame))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if came:
        previous(signal.SIGINT, came[0])
