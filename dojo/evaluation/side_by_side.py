"""The routes of one run side by side: the episodes the chosen backend runs and those sent to the fallback
(`routing`) evaluated at the same time.

Why. `dojo run backend=mjx` sends the episodes of tasks MJX cannot simulate (scripted actors and events) to the CPU
reference backend. Run one route after the other, the GPU waited for the CPU and the CPU for the GPU: in the
protocol's default run on an H200 (2026-12-03, `dojo run backend=mjx policy=zero suite=robodojo_sim episodes=50
seeds=[0] num_envs=1200`) the 850 episodes on mjx took 889 s, and only then did the 300 on mujoco start, at 0.3 s
a control step for horizons of up to 2,600 steps, while the machine's 16 cores had idled beside the GPU.

How. The first route runs on the calling thread, where an interrupt (Ctrl-C, SIGINT) lands; every other runs in a
process of its own (`run_in_process`), watched by a thread here that relays its finished episodes and step counts
to the run's progress. A process, not a thread: the CPU backend's loop is mostly Python (predicates, actors before
every physics step), and as a thread beside the mjx route it held the GIL that route's host side needs (same
machine and run: bucketing 47.4 s instead of 29.8-30.4 s, the first engine group 72.6 s instead of 43.7 s). Each
loop is the same `evaluate` as ever with its own results-store connection and policy link, given a stop event: the
first route that fails (or the interrupt) sets it, the others stop at their next step (`evaluate.Stopped`), and
the failure is raised once every route has ended, so nothing is left running and every episode recorded so far
stays recorded; those in flight are re-run when the run resumes, as after any interrupt.
"""

from __future__ import annotations

import logging
import multiprocessing
import pickle
import queue
import threading
from collections.abc import Callable, Sequence
from typing import Any

from dojo.evaluation.episode import EpisodeResult
from dojo.evaluation.evaluate import ProgressSink, Stopped
from dojo.evaluation.termination import stopping_on_sigterm

JOIN_S = 60.0
"""How long a route's process is given to end after it was told to stop before it is terminated."""
POLL_S = 0.2
"""At most this long between two looks of the thread watching a route's process at the stop event, and, while it
has nothing to relay, at whether the process still lives."""

Route = Callable[[threading.Event], Any]
"""One route's evaluation, given the stop event it must pass to `evaluate`."""


def run_side_by_side(routes: Sequence[Route]) -> None:
    """Run `routes[0]` here and each other route on a thread of its own; return when every one has ended. The
    first error among them, or an interrupt here, stops the others at their next step and is raised once they have
    all ended."""
    stop = threading.Event()
    errors: list[BaseException] = []

    def guarded(route: Route) -> None:
        try:
            route(stop)
        except Stopped:
            pass  # another route failed or the run was interrupted: that is the error raised
        except BaseException as err:  # noqa: BLE001 - an interrupt here included: it stops every route
            errors.append(err)
            stop.set()

    threads = [threading.Thread(target=guarded, args=(route,), name=f"dojo-route-{k}")
               for k, route in enumerate(routes[1:], 1)]
    for thread in threads:
        thread.start()
    guarded(routes[0])
    for thread in threads:
        while thread.is_alive():
            try:
                thread.join()
            except KeyboardInterrupt as err:  # interrupted while the first route had already ended
                errors.append(err)
                stop.set()
    if errors:
        raise errors[0]


class SharedProgress(ProgressSink):
    """A progress sink that the loops of several routes report to, one at a time."""

    def __init__(self, progress: ProgressSink) -> None:
        self._progress = progress
        self._lock = threading.Lock()

    def episode_finished(self, row: EpisodeResult) -> None:
        with self._lock:
            self._progress.episode_finished(row)

    def interactions(self, n: int) -> None:
        with self._lock:
            self._progress.interactions(n)


class _Relay(ProgressSink):
    """A route process's progress sink: each finished episode and step count sent to the watching thread."""

    def __init__(self, messages: Any) -> None:
        self._messages = messages

    def episode_finished(self, row: EpisodeResult) -> None:
        self._messages.put(("row", row))

    def interactions(self, n: int) -> None:
        self._messages.put(("steps", n))


def _route_process(job: Callable[..., int], messages: Any, halt: Any) -> None:
    """A route process's body: `job(halt, progress=...)`, then one last message: done (episodes run), stopped, or
    the error (itself where it pickles, else its text)."""
    logging.basicConfig(level=logging.INFO, format="%(message)s")  # the loop's closing line, as the run's own
    try:  # a SIGTERM to the whole job (a scheduler's) stops this route as it stops the run
        with stopping_on_sigterm():
            messages.put(("done", job(halt, progress=_Relay(messages))))
    except (Stopped, KeyboardInterrupt) as err:  # told to stop, or the run's Ctrl-C reached this process too
        messages.put(("stopped", str(err)))
    except BaseException as err:  # noqa: BLE001 - reported to the run, which raises it
        try:
            pickle.dumps(err)
        except Exception:  # noqa: BLE001 - an error that does not pickle travels as its text
            err = RuntimeError(f"{type(err).__name__}: {err}")
        messages.put(("error", err))


def run_in_process(job: Callable[..., int], progress: ProgressSink, stop: threading.Event) -> int:
    """Run `job` (called as `job(stop_event, progress=sink)`, picklable) in a spawned process, relaying its finished
    episodes and step counts to `progress`; return what it returns. `stop` set here stops it at its next step
    (`Stopped` is raised here then); its error is raised here; a process that dies without a word raises too."""
    context = multiprocessing.get_context("spawn")  # no fork under JAX's and Warp's threads
    messages, halt = context.Queue(), context.Event()
    process = context.Process(target=_route_process, args=(job, messages, halt), name="dojo-route", daemon=True)
    process.start()
    try:
        while True:
            if stop.is_set():
                halt.set()
            try:
                kind, value = messages.get(timeout=POLL_S)
            except queue.Empty:
                if not process.is_alive():
                    raise RuntimeError(f"a route's process ended without a word (exit code {process.exitcode})")
                continue
            if kind == "row":
                progress.episode_finished(value)
            elif kind == "steps":
                progress.interactions(value)
            elif kind == "done":
                return int(value)
            elif kind == "stopped":
                raise Stopped(value)
            else:
                raise value
    finally:
        halt.set()  # a no-op once it has ended; otherwise (an error here) it stops at its next step
        process.join(JOIN_S)
        if process.is_alive():  # stuck in a step (a policy server that does not answer): not left behind
            process.terminate()
            process.join()
