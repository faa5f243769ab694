"""SIGTERM stops a `dojo` job as Ctrl-C does (`dojo.evaluation.termination`)."""

from __future__ import annotations

import os
import signal
import time

import pytest

from dojo.evaluation.termination import EXIT_CODE, Terminated, _raise, stop_on_sigterm


@pytest.fixture
def sigterm_restored():
    before = signal.getsignal(signal.SIGTERM)
    yield
    signal.signal(signal.SIGTERM, before)


def test_sigterm_raises_an_interrupt_once_asked_to(sigterm_restored) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    stop_on_sigterm()
    assert signal.getsignal(signal.SIGTERM) is _raise
    with pytest.raises(KeyboardInterrupt) as caught:  # every path an interrupt takes, SIGTERM takes
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)
    assert isinstance(caught.value, Terminated) and str(caught.value) == "stopped by SIGTERM"
    assert EXIT_CODE == 143


def test_a_disposition_the_parent_chose_is_kept(sigterm_restored) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    stop_on_sigterm()
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN
    mine = lambda signum, frame: None  # noqa: E731
    signal.signal(signal.SIGTERM, mine)
    stop_on_sigterm()
    assert signal.getsignal(signal.SIGTERM) is mine
