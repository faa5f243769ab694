"""The routes of one run side by side: the episodes the chosen backend runs and those sent to the fallback
(`routing`) evaluated at the same time, on threads of this process.

Why. `dojo run backend=mjx` sends the episodes of tasks MJX cannot simulate (scripted actors and events) to the CPU
reference backend. Run one route after the other, the GPU waited for the CPU and the CPU for the GPU: in the
protocol's default run on an H200 (2026-12-03, `dojo run backend=mjx policy=zero suite=robodojo_sim episodes=50
seeds=[0] num_envs=1200`) the 850 episodes on mjx took 889 s, and only then did the 300 on mujoco start, at 0.3 s
a control step for horizons of up to 2,600 steps, while the machine's 16 cores had idled beside the GPU.

How. The first route runs on the calling thread, where an interrupt (Ctrl-C, SIGINT) lands, and every other on a
thread of its own. Each loop is the same `evaluate` as ever, given one shared stop event: the first loop that fails
(or the interrupt) sets it, the others stop at their next step (`evaluate.Stopped`), and the failure is raised once
every thread has ended, so nothing is left running and every episode recorded so far stays recorded; those in
flight are re-run when the run resumes, as after any interrupt. What the loops share has to allow it: a progress
display takes one loop at a time (`SharedProgress`); the results store and the policy link are opened once per
route by the caller (an sqlite3 connection serves one thread; a policy link is one conversation).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import Any

from dojo.evaluation.episode import EpisodeResult
from dojo.evaluation.evaluate import ProgressSink, Stopped

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
