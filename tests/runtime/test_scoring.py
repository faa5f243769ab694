"""Scoring against hand-computed examples (numbers worked out in the comments)."""

from __future__ import annotations

import math

import pytest

from dojo.report.scoring import Replicate, ScoringError, relative_drop, score_episodes, stat


@pytest.fixture
def one_seed_run(make_row, make_task_rows):
    """Seven tasks over the five dimensions, one seed. Hand-computed (success %, score):

    generalization  G1: std (T,100) (F,50), rnd (F,0) (F,20)      -> 25 %, 42.5
                    G2: std (T,100) (T,100), rnd (T,100) (F,40)   -> 75 %, 85
                    dimension                                    -> 50 %, 63.75
    memory          M1: (F,0) (F,0)                               ->  0 %, 0
    precision       P1: (T,100) (F,30) (F,30) (F,0)               -> 25 %, 40
    long_horizon    L1: (T,100) -> 100 %, 100;  L2: (F,10) (F,30) -> 0 %, 20;  dimension 50 %, 60
    open            O1: (F,0) (F,50)                              ->  0 %, 25
    overall = mean of dimension means: success (50+0+25+50+0)/5 = 25, score (63.75+0+40+60+25)/5 = 37.75
    (the mean over the 7 tasks would be 32.14 % / 44.64: a different number.)
    """
    rows = []
    rows += make_task_rows("G1", "generalization", [(True, 100), (False, 50)], setting="standard")
    rows += make_task_rows("G1", "generalization", [(False, 0), (False, 20)], first_episode=2, setting="random")
    rows += make_task_rows("G2", "generalization", [(True, 100), (True, 100)], setting="standard")
    rows += make_task_rows("G2", "generalization", [(True, 100), (False, 40)], first_episode=2, setting="random")
    rows += make_task_rows("M1", "memory", [(False, 0), (False, 0)])
    rows += make_task_rows("P1", "precision", [(True, 100), (False, 30), (False, 30), (False, 0)])
    rows += make_task_rows("L1", "long_horizon", [(True, 100)])
    rows += make_task_rows("L2", "long_horizon", [(False, 10), (False, 30)])
    rows += make_task_rows("O1", "open", [(False, 0), (False, 50)])
    return rows


def test_task_and_dimension_means(one_seed_run):
    scores = score_episodes(one_seed_run)
    tasks = {t.task: t for t in scores.tasks}
    assert tasks["G1"].metrics.success.mean == pytest.approx(25.0)
    assert tasks["G1"].metrics.score.mean == pytest.approx(42.5)
    assert tasks["G2"].metrics.score.mean == pytest.approx(85.0)
    assert tasks["P1"].metrics.score.mean == pytest.approx(40.0)
    assert tasks["G1"].episodes == 4
    dims = {d: s.metrics for d, s in scores.dimensions.items()}
    assert dims["generalization"].success.mean == pytest.approx(50.0)
    assert dims["generalization"].score.mean == pytest.approx(63.75)
    assert dims["long_horizon"].success.mean == pytest.approx(50.0)
    assert dims["long_horizon"].score.mean == pytest.approx(60.0)
    assert scores.dimensions["long_horizon"].tasks == ("L1", "L2")


def test_overall_is_the_mean_of_dimension_means_not_of_tasks(one_seed_run):
    scores = score_episodes(one_seed_run)
    assert scores.overall.success.mean == pytest.approx(25.0)
    assert scores.overall.score.mean == pytest.approx(37.75)
    task_mean_success = sum(t.metrics.success.mean for t in scores.tasks) / len(scores.tasks)
    assert task_mean_success == pytest.approx(225 / 7)
    assert not math.isclose(scores.overall.success.mean, task_mean_success)
    assert not scores.partial and scores.missing_dimensions == ()
    assert list(scores.dimensions) == ["generalization", "precision", "long_horizon", "memory", "open"]


def test_generalization_standard_vs_random(one_seed_run):
    """standard: G1 50 %/75, G2 100 %/100 -> 75 %, 87.5; random: G1 0 %/10, G2 50 %/70 -> 25 %, 40;
    relative drop of the score (87.5 - 40) / 87.5 = 0.542857, of the success (75 - 25) / 75 = 2/3."""
    gen = score_episodes(one_seed_run).generalization
    assert gen.standard.success.mean == pytest.approx(75.0)
    assert gen.standard.score.mean == pytest.approx(87.5)
    assert gen.random.success.mean == pytest.approx(25.0)
    assert gen.random.score.mean == pytest.approx(40.0)
    assert gen.relative_drop_score == pytest.approx(47.5 / 87.5)
    assert gen.relative_drop_success == pytest.approx(2 / 3)
    tasks = {t.task: t for t in score_episodes(one_seed_run).tasks}
    assert tasks["G1"].settings["random"].score.mean == pytest.approx(10.0)


def test_relative_drop_matches_the_paper_example():
    # Hy-Embodied-0.5-VLA in the paper: standard 21.98, random 1.57 -> 92.9 % relative drop.
    assert round(100 * relative_drop(21.98, 1.57), 1) == 92.9
    assert relative_drop(0.0, 0.0) is None


def test_mean_and_sample_std_over_seeds(make_task_rows):
    """One Memory task, 5 episodes per seed, 1/2/3 successes: 20, 40, 60 % -> mean 40, sample std 20
    (population std would be 16.33)."""
    rows = []
    for seed, successes in enumerate((1, 2, 3)):
        outcomes = [(i < successes, 100.0 if i < successes else 0.0) for i in range(5)]
        rows += make_task_rows("M1", "memory", outcomes, eval_seed=seed)
    scores = score_episodes(rows)
    task = scores.tasks[0]
    assert task.metrics.success.values == pytest.approx((20.0, 40.0, 60.0))
    assert task.metrics.success.mean == pytest.approx(40.0)
    assert task.metrics.success.std == pytest.approx(20.0)
    assert scores.overall.success.std == pytest.approx(20.0)
    assert scores.replicates == (Replicate("run-a", 0), Replicate("run-a", 1), Replicate("run-a", 2))


def test_overall_std_is_over_per_seed_overalls(make_task_rows):
    """Each seed succeeds on exactly one (different) dimension: every seed's overall is 20 %, so the overall
    std is 0 although each such dimension swings 100/0/0 (mean 33.33, std 57.735)."""
    rows = []
    winners = {0: "generalization", 1: "memory", 2: "precision"}
    for seed, winner in winners.items():
        for dim in ("generalization", "memory", "precision", "long_horizon", "open"):
            ok = dim == winner
            rows += make_task_rows(f"task_{dim}", dim, [(ok, 100.0 if ok else 0.0)] * 2, eval_seed=seed,
                                   setting="standard")
    scores = score_episodes(rows)
    assert scores.overall.success.values == pytest.approx((20.0, 20.0, 20.0))
    assert scores.overall.success.std == pytest.approx(0.0)
    gen = scores.dimensions["generalization"].metrics.success
    assert gen.mean == pytest.approx(100 / 3)
    assert gen.std == pytest.approx(math.sqrt(((100 - 100 / 3) ** 2 + 2 * (100 / 3) ** 2) / 2))


def test_replicates_are_run_and_eval_seed_pairs(make_task_rows):
    """Three training-seed checkpoints evaluated as three runs with the same eval seed are three replicates."""
    rows = []
    for run, successes in (("ckpt-1", 1), ("ckpt-2", 0), ("ckpt-3", 2)):
        rows += make_task_rows("P1", "precision", [(i < successes, 0.0) for i in range(2)], run_id=run)
    scores = score_episodes(rows)
    assert len(scores.replicates) == 3
    assert scores.overall.success.values == pytest.approx((50.0, 0.0, 100.0))


def test_single_seed_has_no_std(one_seed_run):
    scores = score_episodes(one_seed_run)
    assert scores.overall.success.std is None
    assert stat([3.0]).std is None
    assert stat([1.0, 3.0]).std == pytest.approx(math.sqrt(2))


def test_missing_dimension_gives_a_partial_overall(make_task_rows):
    rows = make_task_rows("P1", "precision", [(True, 100.0), (False, 0.0)])  # 50 %, 50
    rows += make_task_rows("O1", "open", [(False, 10.0), (False, 0.0)])  # 0 %, 5
    scores = score_episodes(rows)
    assert scores.partial
    assert scores.missing_dimensions == ("generalization", "long_horizon", "memory")
    assert scores.overall.success.mean == pytest.approx(25.0)
    assert scores.overall.score.mean == pytest.approx(27.5)
    assert scores.generalization is None


def test_hidden_rows_are_not_scored(make_task_rows):
    rows = make_task_rows("P1", "precision", [(True, 100.0)])
    rows += make_task_rows("P1", "precision", [(False, 0.0)] * 3, split="hidden", first_episode=10)
    assert score_episodes(rows).overall.success.mean == pytest.approx(100.0)
    assert score_episodes(rows, split="hidden").overall.success.mean == pytest.approx(0.0)


def test_uneven_replicates_are_noted(make_task_rows):
    rows = make_task_rows("P1", "precision", [(True, 100.0)] * 2, eval_seed=0)
    rows += make_task_rows("P1", "precision", [(True, 100.0)] * 3, eval_seed=1)
    rows += make_task_rows("P2", "precision", [(False, 0.0)], eval_seed=0)
    notes = score_episodes(rows).notes
    assert any("P1 has different episode counts" in n for n in notes)
    assert any("P2 was evaluated in 1 of 2" in n for n in notes)


def test_inconsistent_input_is_rejected(make_row):
    with pytest.raises(ScoringError):
        score_episodes([])
    with pytest.raises(ScoringError, match="two dimensions"):
        score_episodes([make_row(task="t", dimension="memory"), make_row(task="t", dimension="open", episode=1)])
