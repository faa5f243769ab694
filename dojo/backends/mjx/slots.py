"""The mjx backend's slots as arrays: which bucket row each slot occupies and where its episode stands.

A batched backend steps thousands of slots a tick, and everything the host does per slot and tick is time the GPU
waits. Kept as one object per slot, reading a tick's outputs into them, deciding which episodes ended, scattering
actions into bucket rows and building the result cost about as much host time as the GPU's physics took (27 ms a
tick at 2,048 slots on the 2-core CI machine, 11 ms of it reading outputs). Here each is a few array operations
per bucket of the tick; only what stays Python per slot is per slot: its plan, its end reason once it ended, and
its stage and term maps, which are rebuilt only for slots whose row of them changed this tick (a map is replaced,
never changed in place, so a result hands out the maps as they are).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from dojo.backends.base import END_HORIZON, END_NONFINITE, END_SUCCESS, Observation, StepResult, raise_ended
from dojo.backends.program_types import ProgramLayout

FREE = -1
"""A bucket row no slot occupies (`SlotTable.rows`)."""


def bucket_rows(slots: int, members: int, taken: int = 0) -> int:
    """The rows a bucket needs for a whole run of `slots` slots: one for each of its `members` (plans) the slots
    can hold at once, so that any refill finds a free row and the program compiled at load serves to the end; and
    at least the `taken` rows its first slots occupy (one plan may play in several slots). `dojo bench kernels`
    sizes its lanes by this rule too, since MuJoCo Warp specialises some kernels on a lane's number of worlds."""
    return max(taken, min(slots, members))


class _Read:
    """The stage and term rows of one bucket the slots' maps show, per bucket row; `valid` False until a row's
    episode has been read once (a row that starts an episode is read afresh)."""

    def __init__(self, rows: int, stages: int, terms: int) -> None:
        self.stage = np.zeros((rows, stages), np.int32)
        self.terms = np.zeros((rows, terms), bool)
        self.valid = np.zeros(rows, bool)


class SlotTable:
    """Per slot (0 .. n-1): its plan, bucket and row, steps taken, whether and why its episode ended, its success,
    score and clipped count, and its stage and term maps; per bucket: which slot each row holds (`FREE`: none)."""

    def __init__(self, plans: Sequence[Any], buckets: Sequence[int], rows: Sequence[int],
                 bucket_rows: Sequence[int]) -> None:
        """Slot s plays `plans[s]` in row `rows[s]` of bucket `buckets[s]`; bucket k has `bucket_rows[k]` rows."""
        n = len(plans)
        self.plans = list(plans)
        self.bucket = np.asarray(buckets, np.int64).reshape(n)
        self.row = np.asarray(rows, np.int64).reshape(n)
        self.rows = [np.full(size, FREE, np.int64) for size in bucket_rows]
        for s in range(n):
            self.rows[self.bucket[s]][self.row[s]] = s
        self.horizon = np.asarray([p.horizon for p in plans], np.int64).reshape(n)
        self.step = np.zeros(n, np.int64)
        self.done = np.zeros(n, bool)
        self.success = np.zeros(n, bool)
        self.score = np.zeros(n, np.float32)
        self.clipped_total = np.zeros(n, np.int64)
        self.end_reason: list[str | None] = [None] * n
        self.stage_times: list[dict[str, int | None]] = [{} for _ in range(n)]
        self.terms: list[dict[str, bool]] = [{} for _ in range(n)]
        self._read: dict[int, _Read] = {}

    def __len__(self) -> int:
        return len(self.plans)

    def move(self, s: int, plan: Any, bucket: int, row: int) -> None:
        """Slot `s` will play `plan` in `row` of `bucket` (its old row freed); `restart` then starts the episode."""
        self.rows[self.bucket[s]][self.row[s]] = FREE
        self.plans[s], self.bucket[s], self.row[s] = plan, bucket, row
        self.rows[bucket][row] = s
        self.horizon[s] = plan.horizon

    def restart(self, ids: np.ndarray) -> None:
        """Slots `ids` start their plans' episodes from the beginning."""
        self.step[ids], self.done[ids], self.success[ids] = 0, False, False
        self.score[ids], self.clipped_total[ids] = 0.0, 0
        for s in ids.tolist():
            self.end_reason[s], self.stage_times[s], self.terms[s] = None, {}, {}
            read = self._read.get(int(self.bucket[s]))
            if read is not None:
                read.valid[self.row[s]] = False

    def refuse_ended(self, ids: np.ndarray) -> None:
        """Stepping a slot whose episode ended is the caller's mistake: `EpisodeDone` naming them."""
        ended = ids[self.done[ids]]
        if ended.size:
            raise_ended({int(s): self.end_reason[s] for s in ended.tolist()})

    def by_bucket(self, ids: np.ndarray) -> list[tuple[int, np.ndarray]]:
        """(bucket, positions in `ids` of its slots) for every bucket among slots `ids`."""
        buckets = self.bucket[ids]
        if buckets.size and (buckets == buckets[0]).all():  # one bucket: the common case, no grouping
            return [(int(buckets[0]), np.arange(ids.size))]
        return [(int(k), np.flatnonzero(buckets == k)) for k in np.unique(buckets)]

    def flags(self, ids: np.ndarray) -> list[np.ndarray]:
        """Per bucket, a bool per row: True at the rows of slots `ids`."""
        flags = [np.zeros(len(r), bool) for r in self.rows]
        for k, at in self.by_bucket(ids):
            flags[k][self.row[ids[at]]] = True
        return flags

    def next_steps(self) -> list[np.ndarray]:
        """Per bucket, int32 per row: the control step its slot's episode completes next (0 for a free row)."""
        return [np.where(rows >= 0, self.step[np.maximum(rows, 0)] + 1, 0).astype(np.int32) for rows in self.rows]

    def advance(self, ids: np.ndarray, bad: np.ndarray, outputs: Sequence[Mapping[str, np.ndarray]],
                layout_of: Callable[[int], ProgramLayout]) -> np.ndarray:
        """Each slot's episode after a tick, from its row of `outputs` (per bucket); a slot whose action had a NaN
        or an infinity (`bad`) ends there, its score and steps as before. `layout_of(s)`: slot s's stage and term
        names. Returns the elements clipped per slot."""
        clipped = np.zeros(ids.size, np.int32)
        for s in ids[bad].tolist():
            self.done[s], self.success[s], self.end_reason[s] = True, False, END_NONFINITE
        good_at = np.flatnonzero(~bad)
        good = ids[good_at]
        for k, at in self.by_bucket(good):
            slots, out = good[at], outputs[k]
            rows = self.row[slots]
            count = np.asarray(out["clipped"])[rows]
            clipped[good_at[at]] = count
            self.clipped_total[slots] += count
            self.success[slots] = np.asarray(out["success"])[rows]
            self.score[slots] = np.asarray(out["score"])[rows]
            self.step[slots] += 1
            self._read_maps(k, slots, rows, np.asarray(out["stage_step"])[rows], np.asarray(out["terms"])[rows],
                            layout_of)
        success = self.success[good]
        ended = success | (self.step[good] >= self.horizon[good])
        self.done[good] = ended
        for s, won in zip(good[ended].tolist(), success[ended].tolist()):
            self.end_reason[s] = END_SUCCESS if won else END_HORIZON
        return clipped

    def _read_maps(self, bucket: int, slots: np.ndarray, rows: np.ndarray, stage: np.ndarray, terms: np.ndarray,
                   layout_of: Callable[[int], ProgramLayout]) -> None:
        """Rebuild the stage and term maps of the slots whose rows of them changed (or were never read)."""
        read = self._read.get(bucket)
        if read is None:
            read = self._read[bucket] = _Read(len(self.rows[bucket]), stage.shape[1], terms.shape[1])
        changed = ~read.valid[rows] | (stage != read.stage[rows]).any(axis=1) | (terms != read.terms[rows]).any(axis=1)
        if not changed.any():
            return
        at = np.flatnonzero(changed)
        for s, stage_row, term_row in zip(slots[at].tolist(), stage[at].tolist(), terms[at].tolist()):
            layout = layout_of(s)
            self.stage_times[s] = {n: (t if t >= 0 else None) for n, t in zip(layout.stage_names, stage_row)}
            self.terms[s] = dict(zip(layout.term_names, term_row))
        read.stage[rows[at]], read.terms[rows[at]], read.valid[rows[at]] = stage[at], terms[at], True

    def result(self, ids: np.ndarray, obs: Sequence[Observation], clipped: np.ndarray) -> StepResult:
        """The step's result for slots `ids` (the maps handed out as they are: they are replaced, never changed)."""
        positions = ids.tolist()
        return StepResult(
            env_ids=ids, obs=obs, success=self.success[ids], score=self.score[ids], done=self.done[ids],
            steps=self.step[ids].astype(np.int32), stage_times=[self.stage_times[s] for s in positions],
            end_reason=[self.end_reason[s] for s in positions], clipped=clipped,
            clipped_total=self.clipped_total[ids].astype(np.int32), terms=[self.terms[s] for s in positions])
