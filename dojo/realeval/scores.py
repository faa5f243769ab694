"""Real trials' results once raters have scored them: where the policies are named again.

The console and the rater pages never name a policy; the results store does (each trial's row), and its
`ratings` table holds the raters' marks. `real_scores` joins them per policy and task: trials run, settled
(three ratings in agreement), flagged for adjudication, still open, and over the settled trials the success
rate and the mean score, as the paper reports real-world results.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

from dojo.evaluation.results_store import ResultsStore
from dojo.realeval.ratings import RatingStore, judge


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


def real_scores(store_path: Path) -> list[TaskScore]:
    """Every policy's real trials in the store at `store_path`, judged from their ratings, by policy and task."""
    with ResultsStore(store_path, readonly=True) as store:
        rows = store.rows()
    ratings = RatingStore(store_path)
    try:
        groups: dict[tuple[str, str], list[tuple[object, int]]] = defaultdict(list)
        for row in rows:
            groups[(row.policy_name, row.task)].append(
                (judge(ratings.ratings(row.run_id, row.key)), len(ratings.appeals(row.run_id, row.key))))
    finally:
        ratings.close()
    out = []
    for (policy, task), judged in sorted(groups.items()):
        settled = [v for v, _ in judged if v.settled]  # type: ignore[attr-defined]
        flagged = sum(1 for v, _ in judged if v.flagged)  # type: ignore[attr-defined]
        out.append(TaskScore(
            policy=policy, task=task, trials=len(judged), settled=len(settled), flagged=flagged,
            open=len(judged) - len(settled) - flagged,
            success_rate=100.0 * sum(v.success for v in settled) / len(settled) if settled else None,
            score=sum(v.score for v in settled) / len(settled) if settled else None,
            appeals=sum(n for _, n in judged)))
    return out
