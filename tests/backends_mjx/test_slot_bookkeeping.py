"""The mjx backend's per-slot bookkeeping after a tick (`_advance`): each bucket's outputs read once, a slot's stage
and term maps rebuilt only when their row changed, the episode's end decided as before."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from dojo.backends.mjx.backend import MjxBackend, _Slot


def _outputs(stage: list[int], terms: list[bool], success: bool = False, score: float = 0.0) -> list[dict]:
    """One bucket of two rows; row 1 is the slot's, row 0 another environment's."""
    return [{"clipped": np.asarray([0, 1], np.int32), "success": np.asarray([False, success]),
             "score": np.asarray([0.0, score], np.float32), "stage_step": np.asarray([[-1, -1], stage], np.int32),
             "terms": np.asarray([[False, False], terms])}]


def test_stage_and_term_maps_follow_their_rows_and_are_rebuilt_only_when_they_change():
    backend = MjxBackend(impl="jax")
    backend._stage_layouts = {"p": SimpleNamespace(stage_names=("grasp", "place"), term_names=("up", "in"))}
    slot = _Slot(SimpleNamespace(hash="p", horizon=4), 0, 1)
    fine = np.zeros(1, bool)

    clipped = backend._advance([slot], fine, _outputs([-1, -1], [False, False]))
    first = slot.stage_times
    assert first == {"grasp": None, "place": None} and slot.terms == {"up": False, "in": False}
    assert clipped.tolist() == [1] and slot.clipped_total == 1 and slot.step == 1 and not slot.done

    backend._advance([slot], fine, _outputs([-1, -1], [False, False]))
    assert slot.stage_times is first and slot.step == 2  # nothing changed: the same map, not a new one

    backend._advance([slot], fine, _outputs([3, -1], [True, False], score=50.0))
    assert slot.stage_times == {"grasp": 3, "place": None} and slot.terms == {"up": True, "in": False}
    assert first == {"grasp": None, "place": None}  # the map handed out before is left as it was
    assert slot.score == 50.0 and type(slot.score) is float and not slot.done

    backend._advance([slot], fine, _outputs([3, -1], [True, False], score=50.0))
    assert slot.done and slot.end_reason is not None and not slot.success  # the horizon, 4 steps

    fresh = _Slot(slot.plan, 0, 1)  # a reset: the next episode reads its maps anew
    backend._advance([fresh], fine, _outputs([3, -1], [True, False]))
    assert fresh.stage_times == {"grasp": 3, "place": None} and fresh.stage_times is not slot.stage_times


def test_a_nonfinite_action_ends_the_slot_without_reading_its_row():
    backend = MjxBackend(impl="jax")
    slot = _Slot(SimpleNamespace(hash="p", horizon=4), 0, 1)
    backend._advance([slot], np.ones(1, bool), _outputs([0, 0], [True, True], success=True))
    assert slot.done and not slot.success and slot.step == 0 and slot.stage_times == {}
