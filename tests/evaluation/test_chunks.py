"""The run loop's action chunks as arrays: each slot plays its chunk row by row, then needs a new one."""

from __future__ import annotations

import numpy as np
import pytest

from dojo.evaluation.chunks import ChunkQueue


def test_slots_play_their_chunks_row_by_row_and_then_need_new_ones():
    queue = ChunkQueue(3)
    every = np.arange(3)
    assert queue.exhausted(every).all()  # nothing to play before the first answer
    chunks = np.arange(3 * 2 * 4, dtype=np.float32).reshape(3, 2, 4)
    queue.fill(every, chunks)
    np.testing.assert_array_equal(queue.take(every), chunks[:, 0])
    assert not queue.exhausted(every).any()
    np.testing.assert_array_equal(queue.take(np.asarray([2, 0])), chunks[[2, 0], 1])  # any subset, in its order
    assert queue.exhausted(every).tolist() == [True, False, True]
    queue.fill(np.asarray([0, 2]), np.full((2, 3, 4), 7.0))  # a longer chunk than before: room is made
    assert queue.take(every).tolist() == [[7.0] * 4, chunks[1, 1].tolist(), [7.0] * 4]
    queue.clear(np.asarray([0]))  # a new episode in slot 0
    assert queue.exhausted(every).tolist() == [True, True, False]


def test_one_action_per_slot_is_a_chunk_of_one_and_the_width_must_not_change():
    queue = ChunkQueue(2)
    queue.fill(np.arange(2), np.ones((2, 14)))
    assert queue.take(np.arange(2)).shape == (2, 14) and queue.exhausted(np.arange(2)).all()
    with pytest.raises(ValueError, match="16 action values, before with 14"):
        queue.fill(np.arange(2), np.ones((2, 1, 16)))
