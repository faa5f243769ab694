"""Who runs which episode when a run is spread over workers, and how no episode is lost or run twice.

The dispatcher holds a run's queue. Workers pull small batches from it (only as many as they have free slots, so
that no worker holds episodes another, idle worker could be running) and report every episode as it ends; the
driver drains the reported rows and writes them to the one results store. What a worker pulled and has not
reported is *outstanding* under its name: when the worker dies, `requeue` puts exactly those episodes back at the
head of the queue, for the others.

Exactly once: a key (plan hash, eval seed, episode) is accepted the first time it is reported and dropped after
that, whoever reports it (a worker declared dead whose last report was still on its way, say); a key reported
while it waits in the queue again is taken out of it. The results store's unique key is the second guard.

This is plain Python, so that its bookkeeping is tested without a cluster; `ray_launcher` runs it as a Ray actor.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from dojo.evaluation.episode import EpisodeKey, EpisodeResult, episode_key

if TYPE_CHECKING:
    from dojo.compiler.episodes import PlannedEpisode


@dataclass
class Drained:
    """What the driver takes from the dispatcher at each poll."""

    rows: list[EpisodeResult]
    interactions: int  # environment steps the workers served since the last poll
    left: int  # episodes queued or outstanding: the run is over when this is 0
    queued: int  # of which in the queue, waiting for a worker


def longest_first(items: Iterable[PlannedEpisode], horizons: dict[str, int]) -> list[PlannedEpisode]:
    """The queue with the episodes of the longest horizons first (in queue order among equals). A run over several
    workers ends when its last episodes do: started last, long episodes leave the other workers idle at the end;
    with the longest first the tail is short ones and the workers finish together. The horizon is an episode's
    length for a policy that fails it, and an upper bound otherwise."""
    return sorted(items, key=lambda item: -horizons.get(item.plan_hash, 0))


class EpisodeDispatcher:
    """A run's queue of episodes, shared by its workers (see the module's docstring)."""

    def __init__(self, items: Iterable[PlannedEpisode]) -> None:
        self.queue: deque[PlannedEpisode] = deque(items)
        self.outstanding: dict[int, dict[EpisodeKey, PlannedEpisode]] = {}  # worker -> pulled, not reported
        self.done: set[EpisodeKey] = set()
        self.dead: set[int] = set()
        self._outbox: list[EpisodeResult] = []
        self._interactions = 0

    def pull(self, worker: int, n: int) -> list[PlannedEpisode]:
        """Up to n episodes for `worker`, now outstanding under its name ([] for a worker declared dead)."""
        if worker in self.dead:
            return []
        taken: list[PlannedEpisode] = []
        mine = self.outstanding.setdefault(worker, {})
        while self.queue and len(taken) < n:
            item = self.queue.popleft()
            key = episode_key(item)
            if key not in self.done:
                mine[key] = item
                taken.append(item)
        return taken

    def report(self, rows: Sequence[EpisodeResult], interactions: int = 0) -> None:
        """Episodes a worker finished (and the environment steps it served since it last said). A report is
        accepted from any worker, one declared dead included: its episodes did end, and each counts once."""
        self._interactions += interactions
        waiting = False
        for row in rows:
            key = EpisodeKey(row.plan_hash, row.eval_seed, row.episode)
            if key in self.done:
                continue
            self.done.add(key)
            holders = [mine for mine in self.outstanding.values() if key in mine]
            for mine in holders:  # the reporter's, or another's that pulled it again after a re-queue
                del mine[key]
            waiting |= not holders  # a dead worker's late report of an episode back in the queue
            self._outbox.append(row)
        if waiting:
            self.queue = deque(item for item in self.queue if episode_key(item) not in self.done)

    def count(self, interactions: int) -> None:
        """Environment steps served, between reports (for the driver's rate and ETA)."""
        self._interactions += interactions

    def requeue(self, worker: int) -> int:
        """`worker` is dead: its outstanding episodes go back to the head of the queue. Returns how many."""
        self.dead.add(worker)
        lost = [item for key, item in self.outstanding.pop(worker, {}).items() if key not in self.done]
        self.queue.extendleft(reversed(lost))
        return len(lost)

    def left(self) -> int:
        """Episodes not reported yet: queued, or outstanding at a worker."""
        return len(self.queue) + sum(len(m) for m in self.outstanding.values())

    def drain(self) -> Drained:
        """The rows reported since the last drain (each exactly once), and the counters."""
        out = Drained(self._outbox, self._interactions, self.left(), len(self.queue))
        self._outbox, self._interactions = [], 0
        return out
