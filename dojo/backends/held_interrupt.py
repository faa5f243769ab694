"""Ctrl-C (and SIGTERM, which `dojo` raises as an interrupt too) held back while a backend's device work is under way,
and delivered the moment it ends.

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


HELD = (signal.SIGINT, signal.SIGTERM)
"""The signals held back: Ctrl-C, and SIGTERM where a handler raises it as an interrupt
(`dojo.evaluation.termination`)."""


@contextmanager
def interrupts_held() -> Iterator[None]:
    """Run the block with SIGINT and SIGTERM held back; once it ends normally, hand the first that came to the
    handler it would have gone to (Python's own raises KeyboardInterrupt there). Only the main thread receives
    signals in Python, so elsewhere the block runs as it is, and so does a signal that has no Python handler
    (ignored, or the default action)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {signum: signal.getsignal(signum) for signum in HELD}
    held = [signum for signum, handler in previous.items() if callable(handler)]
    came: list[tuple[int, FrameType | None]] = []
    for signum in held:
        signal.signal(signum, lambda signum, frame: came.append((signum, frame)))
    try:
        yield
    finally:
        for signum in held:
            signal.signal(signum, previous[signum])
    if came:
        signum, frame = came[0]
        previous[signum](signum, frame)
