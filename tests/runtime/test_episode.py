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
    ("dimension", "DLC"), ("dimension", "long horizon"), ("split", "private"), ("task", ""), ("wall_time_s", -1.0),
    ("stage_times", {"grasp": 1.5}), ("policy_meta", {"weights": np.zeros(2)}), ("failure_reason", 3),
])
def test_bad_values_are_refused(make_row, field, value):
    with pytest.raises(ValueError, match=field):
        make_row(**{field: value})


def test_training_only_dimensions_are_recorded_but_never_scored(make_row, make_task_rows):
    """DLC episodes are rows (`dojo collect` resumes from them), but no score, report or progress line counts
    them: they are not scored dimensions of the taxonomy, and scoring either refuses them or leaves them out."""
    from dojo.compiler.taxonomy import builtin_taxonomy
    from dojo.report.scoring import ScoringError, score_episodes

    taxonomy = builtin_taxonomy()
    assert taxonomy.training_only == ("dlc",) and not set(taxonomy.training_only) & set(taxonomy.scored)
    row = make_row(task="dlc", dimension="dlc", success=np.bool_(True), score=100.0)
    assert row.dimension == "dlc" and row.success is True

    scored = make_task_rows("insert_tubes", "precision", [(False, 25.0), (True, 100.0)])
    dlc = make_task_rows("dlc", "dlc", [(True, 100.0)] * 4, first_episode=10)
    baseline = score_episodes(scored)
    try:
        mixed = score_episodes(scored + dlc)
    except (ScoringError, ValueError):
        return  # refused outright: it cannot count
    assert set(mixed.dimensions) == set(baseline.dimensions) == {"precision"}
    assert "dlc" not in {t.task for t in mixed.tasks}
    assert mixed.overall == baseline.overall
