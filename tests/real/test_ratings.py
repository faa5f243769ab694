"""Blind scoring's arithmetic: a rater's score from the rubric, three ratings settled or flagged, appeals, and the
verdicts by policy and task (`dojo console scores`, and `dojo report` beside simulation), from a real results
store."""

from __future__ import annotations

import json
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from dojo.evaluation.episode import EpisodeResult
from dojo.evaluation.results_store import ResultsStore
from dojo.realeval.ratings import Rating, RatingStore, judge, rubric_score
from dojo.realeval.scores import real_scores
from dojo.report.make_report import report_main

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


def _row(policy: str, task: str, episode: int, backend: str = "real", success: bool = False,
         score: float = 0.0) -> EpisodeResult:
    return EpisodeResult(run_id=f"run-{policy}-{backend}", split="public", plan_hash=f"h-{task}", task=task,
                         dimension="precision", setting="standard", eval_seed=0, episode=episode, scene_seed=episode,
                         policy_name=policy, success=success, score=score, steps=100, wall_time_s=4.0,
                         failure_reason=None if success else "horizon", backend=backend)


def test_verdicts_by_policy_and_task_name_the_policies(tmp_path: Path) -> None:
    path = tmp_path / "results.sqlite"
    rows = [_row("alpha", "cap_it", 0), _row("alpha", "cap_it", 1), _row("beta", "cap_it", 0)]
    with ResultsStore(path) as store:
        store.add_many(rows)
    ratings = RatingStore(path)
    for rater in ("r1", "r2", "r3"):
        ratings.rate("run-alpha-real", rows[0].key, Rating(rater, True, {"picked": True, "placed": True}, 100.0))
        ratings.rate("run-beta-real", rows[2].key, Rating(rater, False, {"picked": True}, 25.0))
    for rater, score in (("r1", 0.0), ("r2", 100.0), ("r3", 0.0)):  # alpha's second trial: flagged
        ratings.rate("run-alpha-real", rows[1].key, Rating(rater, score > 0, {}, score))
    appeal = ratings.appeal("run-alpha-real", rows[1].key, "rater r2 marked a trial that never placed the cap")
    ratings.decide(appeal, "upheld: r2's rating withdrawn")
    assert ratings.appeals("run-alpha-real", rows[1].key)[0]["outcome"] == "upheld: r2's rating withdrawn"
    with pytest.raises(ValueError, match="needs a reason"):
        ratings.appeal("run-alpha-real", rows[1].key, " ")
    ratings.close()

    alpha, beta = real_scores(path)
    assert (alpha.policy, alpha.trials, alpha.settled, alpha.flagged, alpha.open) == ("alpha", 2, 1, 1, 0)
    assert alpha.success_rate == 100.0 and alpha.score == 100.0 and alpha.appeals == 1
    assert (beta.policy, beta.settled, beta.success_rate, beta.score) == ("beta", 1, 0.0, 25.0)
    printed = subprocess.run([sys.executable, "-m", "dojo.cli.main", "console", "scores", str(path)],
                             capture_output=True, text=True, timeout=120)
    assert printed.returncode == 0, printed.stderr
    assert "alpha" in printed.stdout and "beta" in printed.stdout and "100.0" in printed.stdout


def test_dojo_report_shows_real_tasks_beside_simulation_with_the_raters_verdicts(tmp_path: Path, capsys) -> None:
    """Real trials stay out of the simulation leaderboard (a robot reports no score) and appear beside it with the
    verdicts `dojo console scores` computes: settled score, flagged disagreement, appeal."""
    sim, real = tmp_path / "sim" / "results.sqlite", tmp_path / "real" / "results.sqlite"
    with ResultsStore(sim) as store:
        store.add_many([_row("alpha", "sim_task", e, backend="mujoco", success=True, score=100.0) for e in range(2)])
    trials = [_row("alpha", "cap_it", 0), _row("alpha", "cap_it", 1)]
    with ResultsStore(real) as store:
        store.add_many(trials)
    ratings = RatingStore(real)
    for rater, score in (("r1", 75.0), ("r2", 75.0), ("r3", 100.0)):
        ratings.rate("run-alpha-real", trials[0].key, Rating(rater, True, {"picked": True}, score))
    for rater, score in (("r1", 0.0), ("r2", 100.0), ("r3", 0.0)):
        ratings.rate("run-alpha-real", trials[1].key, Rating(rater, score > 0, {}, score))
    ratings.decide(ratings.appeal("run-alpha-real", trials[1].key, "the cap <b>was</b> on"), "rejected")
    ratings.close()

    out = tmp_path / "report"
    assert report_main([str(sim.parent), str(real.parent), f"out={out}"]) == 0
    assert "alpha on cap_it (real): success 100.0%, score 83.3 over 1 settled of 2 trials, 1 flagged, 1 appeal" \
        in capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    (entry,) = report["entries"]
    assert entry["public_episodes"] == 2 and entry["scores"]["overall"]["score"]["mean"] == 100.0  # sim only
    assert report["real"]["tasks"] == [vars(s) for s in real_scores(real)]
    (flagged,) = report["real"]["flagged"]
    assert (flagged["task"], flagged["episode"], flagged["raters"]) == ("cap_it", 1, ["r1", "r2", "r3"])
    assert "differ by more than 30" in flagged["reason"]
    (appeal,) = report["real"]["appeals"]
    assert (appeal["reason"], appeal["outcome"]) == ("the cap <b>was</b> on", "rejected")
    page = (out / "report.html").read_text()
    assert "Real robots (RealEval)" in page and "<td class=\"num\">83.3</td>" in page
    assert "the cap &lt;b&gt;was&lt;/b&gt; on" in page and "Flagged for adjudication" in page
    with sqlite3.connect(sim) as db:  # the report only reads: no rating tables added to a simulation store
        assert "ratings" not in {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
