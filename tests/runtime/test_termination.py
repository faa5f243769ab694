"""SIGTERM stops a `dojo` job as Ctrl-C does (`dojo.evaluation.termination`)."""

from __future__ import annotations

import os
import signal
import time

import pytest

from dojo.evaluation.termination import EXIT_CODE, Terminated, _raise, stopping_on_sigterm


@pytest.fixture
def sigterm_restored():
    before = signal.getsignal(signal.SIGTERM)
    yield
    signal.signal(signal.SIGTERM, before)


def test_sigterm_raises_an_interrupt_within_the_block_and_its_default_is_back_after(sigterm_restored) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    with pytest.raises(KeyboardInterrupt) as caught:  # every path an interrupt takes, SIGTERM takes
        with stopping_on_sigterm():
            assert signal.getsignal(signal.SIGTERM) is _raise
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
    assert isinstance(caught.value, Terminated) and str(caught.value) == "stopped by SIGTERM"
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    assert EXIT_CODE == 143


def test_a_disposition_the_parent_chose_is_kept(sigterm_restored) -> None:
    mine = lambda signum, frame: None  # noqa: E731
    for chosen in (signal.SIG_IGN, mine):
        signal.signal(signal.SIGTERM, chosen)
        with stopping_on_sigterm():
            assert signal.getsignal(signal.SIGTERM) is chosen
        assert signal.getsignal(signal.SIGTERM) is chosen


def test_dojo_called_in_process_leaves_sigterm_as_it_found_it(sigterm_restored) -> None:
    from dojo.cli.main import main

    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    assert main(["list", "tasks"]) == 0
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
