"""A batched step's observations are built when read (`dojo.backends.mjx.observations`): what is read must be what
eager building gave, each read of a position the same object, and reading all of them at once (a reset) must
build them per bucket in one pass with the same result."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from dojo.backends.base import envelope
from dojo.backends.mjx.observations import StepObservations

NAMES = ("joint_pos", "gripper")


def _plan(n: int) -> SimpleNamespace:
    return SimpleNamespace(instruction=f"do {n}", task="t", seed=n, embodiment="arx_x5_bimanual", control_hz=10)


def _case() -> tuple[StepObservations, list[dict]]:
    """Five slots over two buckets (rows out of order), and the observations eager building gives."""
    rng = np.random.default_rng(3)
    states = {0: {"joint_pos": rng.random((4, 14), np.float32), "gripper": rng.random((4, 2), np.float32)},
              1: {"joint_pos": rng.random((3, 14), np.float32), "gripper": rng.random((3, 2), np.float32)}}
    plans, steps, buckets, rows = [_plan(n) for n in range(5)], [3, 0, 7, 1, 2], [1, 0, 0, 1, 0], [2, 3, 0, 0, 1]
    seq = StepObservations(plans, steps, buckets, rows, states)
    eager = [envelope(p, t, {n: states[k][n][r] for n in NAMES}) for p, t, k, r in zip(plans, steps, buckets, rows)]
    return seq, eager


def _same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys() and a["meta"] == b["meta"] and a["instruction"] == b["instruction"]
    assert a["state"].keys() == b["state"].keys()
    for name in a["state"]:
        np.testing.assert_array_equal(a["state"][name], b["state"][name])
        assert a["state"][name].dtype == np.float32


def test_each_read_builds_what_eager_building_gave_once() -> None:
    seq, eager = _case()
    assert len(seq) == 5
    for at in (2, 0, 4):
        _same(seq[at], eager[at])
        assert seq[at] is seq[at]
    _same(seq[-1], eager[4])
    assert seq[-1] is seq[4]
    assert [o["meta"]["step"] for o in seq[1:4]] == [0, 7, 1]
    with pytest.raises(IndexError):
        seq[5]
    with pytest.raises(IndexError):
        seq[-6]


def test_reading_all_at_once_gives_the_same_and_keeps_what_was_read() -> None:
    seq, eager = _case()
    first = seq[3]
    everything = list(seq)
    assert everything[3] is first
    for got, want in zip(everything, eager):
        _same(got, want)
    assert [o for o in seq] == everything and all(a is b for a, b in zip(seq, everything))


def test_fields_added_at_the_step_travel_with_the_observation() -> None:
    seq, eager = _case()
    image = np.full((4, 4, 3), 9, np.uint8)
    seq.add(1, {"images": {"head": image}})
    seq.add(1, {"privileged": {"plan_hash": "h"}})
    seq.add(3, {"images": {"head": image + 1}})
    assert seq[1]["images"]["head"] is image and seq[1]["privileged"] == {"plan_hash": "h"}
    assert "images" not in seq[0] and "images" not in list(seq)[2]
    assert list(seq)[3]["images"]["head"][0, 0, 0] == 10


def test_fields_added_after_a_read_reach_the_observation_read() -> None:
    seq, _ = _case()
    first = seq[2]
    seq.add(2, {"images": {"head": np.zeros((2, 2, 3), np.uint8)}})
    assert seq[2] is first and "images" in first
