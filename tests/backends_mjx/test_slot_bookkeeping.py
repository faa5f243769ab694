"""The mjx backend's slots as arrays (`SlotTable`): a tick's outputs read per bucket, a slot's stage and term maps
rebuilt only when their row changed, the episode's end decided as the CPU backend decides it, rows taken and freed
as slots move between buckets."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from dojo.backends.base import END_HORIZON, END_NONFINITE, END_SUCCESS, EpisodeDone
from dojo.backends.mjx.slots import FREE, SlotTable

LAYOUT = SimpleNamespace(stage_names=("grasp", "place"), term_names=("up", "in"))


def _plan(horizon: int = 4, name: str = "p") -> SimpleNamespace:
    return SimpleNamespace(hash=name, horizon=horizon)


def _outputs(stage: list[int], terms: list[bool], success: bool = False, score: float = 0.0) -> list[dict]:
    """One bucket of two rows; row 1 is the slot's, row 0 another environment's."""
    return [{"clipped": np.asarray([0, 1], np.int32), "success": np.asarray([False, success]),
             "score": np.asarray([0.0, score], np.float32), "stage_step": np.asarray([[-1, -1], stage], np.int32),
             "terms": np.asarray([[False, False], terms])}]


def _advance(table: SlotTable, outputs: list[dict], bad: bool = False) -> np.ndarray:
    return table.advance(np.asarray([0]), np.asarray([bad]), outputs, lambda s: LAYOUT)


def test_stage_and_term_maps_follow_their_rows_and_are_rebuilt_only_when_they_change():
    table = SlotTable([_plan()], [0], [1], [2])
    clipped = _advance(table, _outputs([-1, -1], [False, False]))
    first = table.stage_times[0]
    assert first == {"grasp": None, "place": None} and table.terms[0] == {"up": False, "in": False}
    assert clipped.tolist() == [1] and table.clipped_total[0] == 1 and table.step[0] == 1 and not table.done[0]

    _advance(table, _outputs([-1, -1], [False, False]))
    assert table.stage_times[0] is first and table.step[0] == 2  # nothing changed: the same map, not a new one

    _advance(table, _outputs([3, -1], [True, False], score=50.0))
    assert table.stage_times[0] == {"grasp": 3, "place": None} and table.terms[0] == {"up": True, "in": False}
    assert first == {"grasp": None, "place": None}  # the map handed out before is left as it was
    result = table.result(np.asarray([0]), [{}], np.zeros(1, np.int32))
    assert result.score.tolist() == [50.0] and result.stage_times[0] is table.stage_times[0]
    assert not table.done[0]

    before = table.stage_times[0]
    _advance(table, _outputs([3, -1], [True, False], score=50.0))
    assert table.done[0] and table.end_reason[0] == END_HORIZON and not table.success[0]  # 4 steps
    assert table.stage_times[0] is before

    table.restart(np.asarray([0]))  # the next episode reads its maps anew, even where its row reads the same
    assert table.step[0] == 0 and not table.done[0] and table.end_reason[0] is None
    _advance(table, _outputs([3, -1], [True, False]))
    assert table.stage_times[0] == {"grasp": 3, "place": None} and table.stage_times[0] is not before


def test_success_ends_the_episode_before_its_horizon():
    table = SlotTable([_plan(horizon=10)], [0], [1], [2])
    _advance(table, _outputs([2, 5], [True, True], success=True, score=100.0))
    assert table.done[0] and table.success[0] and table.end_reason[0] == END_SUCCESS and table.step[0] == 1


def test_a_nonfinite_action_ends_the_slot_without_reading_its_row():
    table = SlotTable([_plan()], [0], [1], [2])
    _advance(table, _outputs([0, 0], [True, True], success=True), bad=True)
    assert table.done[0] and not table.success[0] and table.end_reason[0] == END_NONFINITE
    assert table.step[0] == 0 and table.stage_times[0] == {}


def test_slots_of_several_buckets_read_their_own_bucket_and_row():
    # slots 0 and 2 in bucket 1 (rows 1 and 0), slot 1 in bucket 0 (row 0); outputs differ by bucket and row
    table = SlotTable([_plan(), _plan(), _plan()], [1, 0, 1], [1, 0, 0], [1, 2])
    outputs = [{"clipped": np.asarray([7], np.int32), "success": np.asarray([False]),
                "score": np.asarray([10.0], np.float32), "stage_step": np.asarray([[1, -1]], np.int32),
                "terms": np.asarray([[True, False]])},
               {"clipped": np.asarray([3, 5], np.int32), "success": np.asarray([True, False]),
                "score": np.asarray([100.0, 20.0], np.float32), "stage_step": np.asarray([[0, 0], [-1, -1]], np.int32),
                "terms": np.asarray([[True, True], [False, False]])}]
    ids = np.asarray([2, 0, 1])
    clipped = table.advance(ids, np.zeros(3, bool), outputs, lambda s: LAYOUT)
    assert clipped.tolist() == [3, 5, 7]
    assert table.score[ids].tolist() == [100.0, 20.0, 10.0]
    assert table.success[ids].tolist() == [True, False, False] and table.done[ids].tolist() == [True, False, False]
    assert table.stage_times[1] == {"grasp": 1, "place": None} and table.terms[2] == {"up": True, "in": True}
    flags = table.flags(np.asarray([1, 2]))
    assert [f.tolist() for f in flags] == [[True], [True, False]]
    assert [s.tolist() for s in table.next_steps()] == [[2], [2, 2]]


def test_a_move_frees_the_old_row_and_takes_the_new_one():
    table = SlotTable([_plan(), _plan()], [0, 0], [0, 1], [2, 2])
    table.move(1, _plan(horizon=9, name="q"), 1, 0)
    assert table.rows[0].tolist() == [0, FREE] and table.rows[1].tolist() == [1, FREE]
    assert table.horizon[1] == 9 and table.plans[1].hash == "q"
    assert [s.tolist() for s in table.next_steps()] == [[1, 0], [1, 0]]  # free rows complete step 0


def test_stepping_an_ended_slot_is_refused_naming_a_few_of_them():
    table = SlotTable([_plan(horizon=1)] * 20, [0] * 20, list(range(20)), [20])
    ids = np.arange(20)
    outputs = [{"clipped": np.zeros(20, np.int32), "success": np.zeros(20, bool), "score": np.zeros(20, np.float32),
                "stage_step": -np.ones((20, 2), np.int32), "terms": np.zeros((20, 2), bool)}]
    table.advance(ids, np.zeros(20, bool), outputs, lambda s: LAYOUT)
    with pytest.raises(EpisodeDone, match=r"ended in 20 slot\(s\) \{0: 'horizon'.* and 12 more"):
        table.refuse_ended(ids)
    table.restart(ids[:19])
    with pytest.raises(EpisodeDone, match=r"ended in 1 slot\(s\) \{19: 'horizon'\} \(slot"):
        table.refuse_ended(ids)


def test_a_bucket_gets_a_row_for_each_plan_the_slots_can_hold_and_for_each_slot_that_plays_one():
    from dojo.backends.mjx.slots import bucket_rows

    assert bucket_rows(slots=8, members=3) == 3  # every plan of the bucket can run at once
    assert bucket_rows(slots=2, members=50) == 2  # no more than the slots can hold at once
    assert bucket_rows(slots=4, members=1, taken=4) == 4  # one plan in four slots (replicates) takes four rows
