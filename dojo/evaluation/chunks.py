"""The action chunks a run's slots are executing, as arrays: one row of actions per slot and control step.

A policy answers with a chunk of K actions per environment, and the loop plays them one control step at a time.
Kept per slot as NumPy arrays sliced one row per step, that bookkeeping was a Python operation per slot and step
(about 10 ms a step at 2,048 slots on the CI machine, while the GPU waits); here every step is a few array
operations over the slots stepped.
"""

from __future__ import annotations

import numpy as np


class ChunkQueue:
    """Per slot (0 .. n-1): the actions of its current chunk and how many it has played."""

    def __init__(self, slots: int) -> None:
        self.rows = np.zeros((slots, 0, 0), np.float32)  # [slot, row, action]
        self.length = np.zeros(slots, np.int64)  # rows of the slot's current chunk
        self.cursor = np.zeros(slots, np.int64)  # rows of it already played

    def exhausted(self, ids: np.ndarray) -> np.ndarray:
        """Which of slots `ids` have no action left (a new chunk is needed before they step)."""
        return self.cursor[ids] >= self.length[ids]

    def fill(self, ids: np.ndarray, chunks: np.ndarray) -> None:
        """Slots `ids` start the chunks `chunks` ([len(ids), K, D], or [len(ids), D] for one action each) from
        their first row."""
        chunks = np.asarray(chunks, np.float32)
        if chunks.ndim == 2:
            chunks = chunks[:, None, :]
        k, d = chunks.shape[1], chunks.shape[2]
        if self.rows.shape[2] not in (0, d):
            raise ValueError(f"the policy answered with {d} action values, before with {self.rows.shape[2]}")
        if self.rows.shape[2] == 0 or k > self.rows.shape[1]:  # the first chunk, or a longer one: room for it
            grown = np.zeros((len(self.rows), max(k, self.rows.shape[1]), d), np.float32)
            if self.rows.shape[2]:
                grown[:, :self.rows.shape[1]] = self.rows
            self.rows = grown
        self.rows[ids, :k] = chunks
        self.length[ids] = k
        self.cursor[ids] = 0

    def take(self, ids: np.ndarray) -> np.ndarray:
        """The next action of each of slots `ids` ([len(ids), D]; none may be `exhausted`), and move past it."""
        actions = self.rows[ids, self.cursor[ids]]
        self.cursor[ids] += 1
        return actions

    def clear(self, ids: np.ndarray) -> None:
        """Slots `ids` start new episodes: their chunks are dropped."""
        self.length[ids] = 0
        self.cursor[ids] = 0
