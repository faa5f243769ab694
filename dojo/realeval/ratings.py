"""Blind scoring of real trials: raters' marks, their agreement, and appeals, kept in the run's results store.

A real trial's success and score are not measured by the robot: raters watch its video and mark, against the
task's rubric (its score stages), whether the task succeeded and which stages were reached. Each rater's marks
are one row of `ratings` (keyed by the trial and the rater id); the trial's score from a rater is the weighted
fraction of stages marked reached, 0-100, as simulation scores are. With `RATERS_PER_TRIAL` ratings a trial is
settled: the scores are averaged and success is the majority's, unless the raters' scores lie more than
`DISAGREEMENT` points apart or they split on success, which flags it for adjudication instead. An appeal (a
policy's submitter disputes a trial) is recorded with its reason, and later its outcome.

The tables live in the results store's file beside `episodes` (SQLite; their own connection), so that a trial's
row, its video and its ratings travel together, and a report can join them, naming the policy only there.
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dojo.evaluation.episode import EpisodeKey

RATERS_PER_TRIAL = 3
DISAGREEMENT = 30.0
"""Score points: raters further apart than this on one trial flag it for adjudication."""

_SCHEMA = """
CREATE TABLE IF NOT EXISTS ratings (
    run_id TEXT NOT NULL, plan_hash TEXT NOT NULL, eval_seed INTEGER NOT NULL, episode INTEGER NOT NULL,
    rater TEXT NOT NULL, success INTEGER NOT NULL CHECK (success IN (0, 1)), stages TEXT NOT NULL,
    score REAL NOT NULL CHECK (score >= 0 AND score <= 100),
    rated_at TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now')),
    PRIMARY KEY (run_id, plan_hash, eval_seed, episode, rater)
);
CREATE TABLE IF NOT EXISTS appeals (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    run_id TEXT NOT NULL, plan_hash TEXT NOT NULL, eval_seed INTEGER NOT NULL, episode INTEGER NOT NULL,
    reason TEXT NOT NULL, outcome TEXT,
    filed_at TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now'))
);
"""


@dataclass(frozen=True)
class Rating:
    """One rater's marks of one trial."""

    rater: str
    success: bool
    stages: dict[str, bool]
    score: float


@dataclass(frozen=True)
class Verdict:
    """A trial's result from its ratings: settled (mean score, majority success) or flagged, or still open."""

    ratings: tuple[Rating, ...]
    settled: bool
    flagged: bool
    success: bool | None
    score: float | None
    reason: str | None = None


def rubric_score(stages: Sequence[Mapping[str, Any]], marked: Mapping[str, bool]) -> float:
    """The weighted fraction (0-100) of the rubric's `stages` (a plan's program stages) marked reached."""
    total = sum(float(s.get("weight", 1.0)) for s in stages)
    reached = sum(float(s.get("weight", 1.0)) for s in stages if marked.get(s["name"]))
    return 100.0 * reached / total if total else 0.0


def judge(ratings: Sequence[Rating], needed: int = RATERS_PER_TRIAL, disagreement: float = DISAGREEMENT) -> Verdict:
    """Settle a trial from its ratings (see the module docstring)."""
    ratings = tuple(ratings)
    if len(ratings) < needed:
        return Verdict(ratings, settled=False, flagged=False, success=None, score=None,
                       reason=f"{len(ratings)} of {needed} ratings")
    scores = [r.score for r in ratings]
    votes = [r.success for r in ratings]
    if max(scores) - min(scores) > disagreement:
        return Verdict(ratings, settled=False, flagged=True, success=None, score=None,
                       reason=f"scores {min(scores):.0f}..{max(scores):.0f} differ by more than {disagreement:.0f}")
    if len(set(votes)) > 1:
        return Verdict(ratings, settled=False, flagged=True, success=None, score=None,
                       reason=f"success marked by {sum(votes)} of {len(votes)} raters")
    return Verdict(ratings, settled=True, flagged=False, success=votes[0], score=sum(scores) / len(scores))


class RatingStore:
    """The `ratings` and `appeals` tables of the results store at `path` (one instance per thread). `readonly`
    (a report) opens the file read-only and reads a store nobody has rated yet as having no ratings."""

    def __init__(self, path: Path, readonly: bool = False) -> None:
        if readonly:
            self._db = sqlite3.connect(f"{Path(path).resolve().as_uri()}?mode=ro", uri=True, timeout=30.0,
                                       isolation_level=None)
            tables = {r[0] for r in self._db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
            self._empty = not {"ratings", "appeals"} <= tables
        else:
            self._db = sqlite3.connect(path, timeout=30.0, isolation_level=None)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.executescript(_SCHEMA)
            self._empty = False

    def rate(self, run_id: str, key: EpisodeKey, rating: Rating) -> None:
        """Record (or replace: a rater may correct their own marks) one rater's marks of a trial."""
        self._db.execute(
            "INSERT OR REPLACE INTO ratings (run_id, plan_hash, eval_seed, episode, rater, success, stages, score) "
            "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
            (run_id, *key, rating.rater, int(rating.success), json.dumps(rating.stages, sort_keys=True),
             rating.score))

    def ratings(self, run_id: str, key: EpisodeKey) -> list[Rating]:
        if self._empty:
            return []
        rows = self._db.execute(
            "SELECT rater, success, stages, score FROM ratings WHERE run_id = ? AND plan_hash = ? AND eval_seed = ? "
            "AND episode = ? ORDER BY rater", (run_id, *key)).fetchall()
        return [Rating(r[0], bool(r[1]), json.loads(r[2]), float(r[3])) for r in rows]

    def appeal(self, run_id: str, key: EpisodeKey, reason: str) -> int:
        """File an appeal against a trial's result; its id."""
        if not reason.strip():
            raise ValueError("an appeal needs a reason")
        cur = self._db.execute("INSERT INTO appeals (run_id, plan_hash, eval_seed, episode, reason) "
                               "VALUES (?, ?, ?, ?, ?)", (run_id, *key, reason))
        return int(cur.lastrowid)

    def decide(self, appeal_id: int, outcome: str) -> None:
        """Record an appeal's outcome (e.g. 'upheld: re-run the trial', 'rejected: ...')."""
        if self._db.execute("UPDATE appeals SET outcome = ? WHERE id = ?", (outcome, appeal_id)).rowcount != 1:
            raise KeyError(f"no appeal {appeal_id}")

    def appeals(self, run_id: str, key: EpisodeKey) -> list[dict[str, Any]]:
        if self._empty:
            return []
        rows = self._db.execute(
            "SELECT id, reason, outcome, filed_at FROM appeals WHERE run_id = ? AND plan_hash = ? AND eval_seed = ? "
            "AND episode = ? ORDER BY id", (run_id, *key)).fetchall()
        return [{"id": r[0], "reason": r[1], "outcome": r[2], "filed_at": r[3]} for r in rows]

    def close(self) -> None:
        self._db.close()
