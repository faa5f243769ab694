"""EpisodeResult validation: bad values are refused when recorded, numpy scalars become plain Python."""

from __future__ import annotations

import numpy as np
import pytest


def test_numpy_scalars_are_normalised(make_row):
    row = make_row(success=np.bool_(True), score=np.float32(87.5), steps=np.int64(412), eval_seed=np.int32(2),
                   wall_time_s=np.float64(3.25), stage_times={"grasp": np.int64(10), "place": None})
    assert row.success is True and type(row.score) is float and type(row.steps) is int
    assert row.stage_times == {"grasp": 10, "place": None} and type(row.stage_times["grasp"]) is int
    assert row.key == ("stack_bowls-standard-public-0", 2, 0)


@pytest.mark.parametrize("field, value", [
    ("score", 140.0), ("score", float("nan")), ("score", True), ("success", 1), ("steps", 2.5), ("steps", -1),
    ("dimension", "dlc"), ("split", "private"), ("task", ""), ("wall_time_s", -1.0),
    ("stage_times", {"grasp": 1.5}), ("policy_meta", {"weights": np.zeros(2)}), ("failure_reason", 3),
])
def test_bad_values_are_refused(make_row, field, value):
    with pytest.raises(ValueError, match=field):
        make_row(**{field: value})
