"""Blind scoring's arithmetic: a rater's score from the rubric, three ratings settled or flagged, appeals, and the
verdicts by policy and task (`dojo console scores`), from a real results store."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from dojo.evaluation.episode import EpisodeResult
from dojo.evaluation.results_store import ResultsStore
from dojo.realeval.ratings import Rating, RatingStore, judge, rubric_score
from dojo.realeval.scores import real_scores

STAGES = [{"name": "picked", "weight": 1}, {"name": "placed", "weight": 3}]


def test_a_raters_score_is_the_weighted_share_of_stages_marked() -> None:
    assert rubric_score(STAGES, {"picked": True}) == 25.0
    assert rubric_score(STAGES, {"picked": True, "placed": True}) == 100.0
    assert rubric_score(STAGES, {}) == 0.0


def test_three_ratings_settle_a_trial_unless_they_disagree() -> None:
    r = [Rating("a", True, {}, 100.0), Rating("b", True, {}, 75.0), Rating("c", True, {}, 100.0)]
    open_ = judge(r[:2])
    assert not open_.settled and not open_.flagged and open_.reason == "2 of 3 ratings"
    settled = judge(r)
    assert settled.settled and settled.success and settled.score == pytest.approx(275 / 3)
    spread = judge([*r[:2], Rating("c", True, {}, 25.0)])
    assert spread.flagged and "differ by more than 30" in spread.reason
    split = judge([*r[:2], Rating("c", False, {}, 100.0)])
    assert split.flagged and split.reason == "success marked by 2 of 3 raters"


def _row(policy: str, task: str, episode: int) -> EpisodeResult:
    return EpisodeResult(run_id=f"run-{policy}", split="public", plan_hash=f"h-{task}", task=task,
                         dimension="precision", setting="standard", eval_seed=0, episode=episode, scene_seed=episode,
                         policy_name=policy, success=False, score=0.0, steps=100, wall_time_s=4.0,
                         failure_reason="horizon", backend="real")


def test_verdicts_by_policy_and_task_name_the_policies(tmp_path: Path) -> None:
    path = tmp_path / "results.sqlite"
    rows = [_row("alpha", "cap_it", 0), _row("alpha", "cap_it", 1), _row("beta", "cap_it", 0)]
    with ResultsStore(path) as store:
        store.add_many(rows)
    ratings = RatingStore(path)
    for rater in ("r1", "r2", "r3"):
        ratings.rate("run-alpha", rows[0].key, Rating(rater, True, {"picked": True, "placed": True}, 100.0))
        ratings.rate("run-beta", rows[2].key, Rating(rater, False, {"picked": True}, 25.0))
    for rater, score in (("r1", 0.0), ("r2", 100.0), ("r3", 0.0)):  # alpha's second trial: flagged
        ratings.rate("run-alpha", rows[1].key, Rating(rater, score > 0, {}, score))
    appeal = ratings.appeal("run-alpha", rows[1].key, "rater r2 marked a trial that never placed the cap")
    ratings.decide(appeal, "upheld: r2's rating withdrawn")
    assert ratings.appeals("run-alpha", rows[1].key)[0]["outcome"] == "upheld: r2's rating withdrawn"
    with pytest.raises(ValueError, match="needs a reason"):
        ratings.appeal("run-alpha", rows[1].key, " ")
    ratings.close()

    alpha, beta = real_scores(path)
    assert (alpha.policy, alpha.trials, alpha.settled, alpha.flagged, alpha.open) == ("alpha", 2, 1, 1, 0)
    assert alpha.success_rate == 100.0 and alpha.score == 100.0 and alpha.appeals == 1
    assert (beta.policy, beta.settled, beta.success_rate, beta.score) == ("beta", 1, 0.0, 25.0)
    printed = subprocess.run([sys.executable, "-m", "dojo.cli.main", "console", "scores", str(path)],
                             capture_output=True, text=True, timeout=120)
    assert printed.returncode == 0, printed.stderr
    assert "alpha" in printed.stdout and "beta" in printed.stdout and "100.0" in printed.stdout
