"""SIGTERM ends a job as Ctrl-C does: what finished is kept, the backend is closed, and a rerun resumes.

Why. Schedulers and supervisors stop jobs with SIGTERM (SLURM's `scancel` and time limit, `kill`, `docker stop`,
Kubernetes), usually followed by SIGKILL some seconds later. Python's default for SIGTERM is to die on the spot:
the episodes in flight are lost anyway, but so is the closing of the backend, whose device work may still be
running (an mjx run interrupted mid-tick died in its teardown, 2026-12-03), and the line saying why the run
stopped. Raised as a `KeyboardInterrupt`, SIGTERM takes every path an interrupt already takes (the backend's tick
holds it back to the tick's end, `dojo.backends.held_interrupt`; routes stop side by side; the CLI says so).
And a run started in the background from a script (`dojo run ... &`) ignores SIGINT, as the shell makes every
background job do, so SIGTERM is how such a run is stopped cleanly.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

EXIT_CODE = 128 + signal.SIGTERM
"""What a process stopped by SIGTERM exits with, by the shells' convention (143)."""


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived: raised in the main thread wherever Ctrl-C's KeyboardInterrupt would be."""

    def __init__(self) -> None:
        super().__init__("stopped by SIGTERM")


def _raise(signum: int, frame: FrameType | None) -> None:
    raise Terminated()


@contextmanager
def stopping_on_sigterm() -> Iterator[None]:
    """Within the block SIGTERM raises `Terminated` in the main thread, unless the process was given another
    disposition for it (a parent that ignores or handles SIGTERM keeps its choice) or this is not the main thread
    (only it can set handlers). The disposition before is restored after, so that `dojo.cli.main.main` called in
    a process that goes on (a test's) leaves it as it was."""
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield
        return
    signal.signal(signal.SIGTERM, _raise)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
