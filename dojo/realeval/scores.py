"""Real trials' results once raters have scored them: where the policies are named again.

The console and the rater pages never name a policy; the results store does (each trial's row), and its
`ratings` table holds the raters' marks. `real_scores` joins them per policy and task: trials run, settled
(three ratings in agreement), flagged for adjudication, still open, and over the settled trials the success
rate and the mean score, as the paper reports real-world results.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dojo.evaluation.episode import EpisodeResult
from dojo.evaluation.results_store import ResultsStore
from dojo.realeval.ratings import RatingStore, Verdict, judge

REAL_BACKEND = "real"
"""The backend name real trials' rows carry (`EpisodeResult.backend`)."""


@dataclass(frozen=True)
class TaskScore:
    """One policy on one real task."""

    policy: str
    task: str
    trials: int
    settled: int
    flagged: int
    open: int
    success_rate: float | None
    """Percent of settled trials the raters marked successful (None before any is settled)."""
    score: float | None
    """Mean rater score (0-100) of the settled trials."""
    appeals: int


@dataclass(frozen=True)
class JudgedTrial:
    """One real trial's row with its raters' verdict and the appeals filed against it."""

    row: EpisodeResult
    verdict: Verdict
    appeals: tuple[dict[str, Any], ...]


def judged_trials(store_path: Path) -> list[JudgedTrial]:
    """Every real trial (backend `real`) in the store at `store_path`, judged from its ratings (read-only)."""
    with ResultsStore(store_path, readonly=True) as store:
        rows = [r for r in store.rows() if r.backend == REAL_BACKEND]
    if not rows:
        return []
    ratings = RatingStore(store_path, readonly=True)
    try:
        return [JudgedTrial(row, judge(ratings.ratings(row.run_id, row.key)),
                            tuple(ratings.appeals(row.run_id, row.key))) for row in rows]
    finally:
        ratings.close()


def task_scores(trials: Iterable[JudgedTrial]) -> list[TaskScore]:
    """The trials' verdicts by policy and task (see the module docstring)."""
    groups: dict[tuple[str, str], list[JudgedTrial]] = defaultdict(list)
    for trial in trials:
        groups[(trial.row.policy_name, trial.row.task)].append(trial)
    out = []
    for (policy, task), judged in sorted(groups.items()):
        settled = [t.verdict for t in judged if t.verdict.settled]
        flagged = sum(1 for t in judged if t.verdict.flagged)
        out.append(TaskScore(
            policy=policy, task=task, trials=len(judged), settled=len(settled), flagged=flagged,
            open=len(judged) - len(settled) - flagged,
            success_rate=100.0 * sum(bool(v.success) for v in settled) / len(settled) if settled else None,
            score=sum(float(v.score or 0.0) for v in settled) / len(settled) if settled else None,
            appeals=sum(len(t.appeals) for t in judged)))
    return out


def real_scores(store_path: Path) -> list[TaskScore]:
    """Every policy's real trials in the store at `store_path`, judged from their ratings, by policy and task."""
    return task_scores(judged_trials(store_path))
