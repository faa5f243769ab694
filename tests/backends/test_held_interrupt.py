"""Ctrl-C held back over a backend's tick (`dojo.backends.held_interrupt`): delivered once the block ends, to the
handler it would have reached, and nothing changes where Python has no handler or off the main thread."""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from dojo.backends.held_interrupt import interrupts_held


@pytest.fixture
def python_sigint():
    """Python's own SIGINT handler for the test (pytest-xdist's workers ignore SIGINT), restored after."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


def _send(signum: int = signal.SIGINT) -> None:
    os.kill(os.getpid(), signum)
    time.sleep(0.05)  # Python runs the handler at the next bytecode after the signal lands


def test_a_sigint_inside_the_block_is_raised_once_the_block_has_ended(python_sigint) -> None:
    ran = []
    with pytest.raises(KeyboardInterrupt):
        with interrupts_held():
            _send()
            ran.append("the rest of the block")
    assert ran == ["the rest of the block"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    with pytest.raises(KeyboardInterrupt):  # and outside a block, Ctrl-C is Ctrl-C again
        _send()


def test_a_block_without_sigint_ends_quietly_and_a_handler_of_the_caller_gets_the_signal(python_sigint) -> None:
    with interrupts_held():
        pass
    got = []
    signal.signal(signal.SIGINT, lambda signum, frame: got.append(signum))
    with interrupts_held():
        _send()
        assert got == []
    assert got == [signal.SIGINT]


@pytest.mark.parametrize("signum, disposition", [(signal.SIGINT, signal.SIG_IGN), (signal.SIGTERM, signal.SIG_IGN),
                                                 (signal.SIGTERM, signal.SIG_DFL)])
def test_a_signal_without_a_python_handler_is_left_alone(signum, disposition) -> None:
    before = signal.signal(signum, disposition)
    try:
        with interrupts_held():
            assert signal.getsignal(signum) is disposition
    finally:
        signal.signal(signum, before)


def test_off_the_main_thread_the_block_runs_as_it_is() -> None:
    seen = []

    def worker() -> None:
        with interrupts_held():
            seen.append(signal.getsignal(signal.SIGINT))

    thread = threading.Thread(target=worker)
    thread.start()
    thread.join()
    assert seen == [signal.getsignal(signal.SIGINT)]


def test_a_sigterm_raised_as_an_interrupt_is_held_to_the_blocks_end_too() -> None:
    """`dojo` raises SIGTERM as an interrupt (`termination.stopping_on_sigterm`); inside a tick it waits like Ctrl-C."""
    from dojo.evaluation.termination import Terminated, _raise

    before = signal.signal(signal.SIGTERM, _raise)
    try:
        ran = []
        with pytest.raises(Terminated):
            with interrupts_held():
                _send(signal.SIGTERM)
                ran.append("the rest of the block")
        assert ran == ["the rest of the block"]
        assert signal.getsignal(signal.SIGTERM) is _raise
    finally:
        signal.signal(signal.SIGTERM, before)
