"""The results store: one SQLite row per finished episode, committed durably as each episode ends.

Why SQLite in WAL mode: a run must survive `kill -9` at any instant and resume without repeating or losing a
finished episode. Each `add()` is its own transaction with `synchronous=FULL`, so once it returns the row is on
disk; a process killed mid-transaction leaves no partial row (SQLite rolls the journal back on the next open).
WAL lets a reader (a report, a progress dashboard) read a consistent snapshot while the run keeps writing.

Rows are keyed by (run id, plan hash, eval seed, episode index). Writing the same key twice keeps the first
row (`add()` returns False): a resumed run that re-executes an episode by mistake can never duplicate it or
replace the result that was already recorded.
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

from dojo.evaluation.episode import EpisodeKey, EpisodeResult

SCHEMA_VERSION = 4
# What turns a store of each older version into the next one. Writers migrate when they open a store, readers
# read an older store as it is (`_LEGACY_COLUMNS`): a report over last month's runs needs no write access.
_MIGRATIONS: dict[int, str] = {
    1: "ALTER TABLE episodes ADD COLUMN success_terms TEXT NOT NULL DEFAULT '{}'",  # 2: which condition failed
    2: "ALTER TABLE episodes ADD COLUMN counters TEXT NOT NULL DEFAULT '{}'",  # 3: the backend's episode counters
    3: "ALTER TABLE episodes ADD COLUMN backend TEXT NOT NULL DEFAULT ''",  # 4: which backend ran the episode
}
_LEGACY_COLUMNS: dict[int, dict[str, str]] = {1: {"success_terms": "'{}'", "counters": "'{}'", "backend": "''"},
                                              2: {"counters": "'{}'", "backend": "''"}, 3: {"backend": "''"}}
STORE_FILENAME = "results.sqlite"  # the store's name inside a run folder

_COLUMNS: tuple[str, ...] = (
    "run_id", "split", "plan_hash", "task", "dimension", "setting", "eval_seed", "episode", "scene_seed",
    "policy_name", "policy_meta", "success", "score", "stage_times", "steps", "wall_time_s", "failure_reason",
    "video_path", "success_terms", "counters", "backend",
)
_JSON_COLUMNS = frozenset({"policy_meta", "stage_times", "success_terms", "counters"})
_SUCCESS = _COLUMNS.index("success")
_INSERT = (f"INSERT INTO episodes ({', '.join(_COLUMNS)}) VALUES ({', '.join('?' * len(_COLUMNS))}) "
           "ON CONFLICT (run_id, plan_hash, eval_seed, episode) DO NOTHING")

_SCHEMA = f"""
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS runs (
    run_id TEXT PRIMARY KEY,
    created_at TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now')),
    meta TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS episodes (
    run_id TEXT NOT NULL,
    split TEXT NOT NULL CHECK (split IN ('public', 'hidden')),
    plan_hash TEXT NOT NULL,
    task TEXT NOT NULL,
    dimension TEXT NOT NULL,
    setting TEXT NOT NULL,
    eval_seed INTEGER NOT NULL,
    episode INTEGER NOT NULL,
    scene_seed INTEGER NOT NULL,
    policy_name TEXT NOT NULL,
    policy_meta TEXT NOT NULL,
    success INTEGER NOT NULL CHECK (success IN (0, 1)),
    score REAL NOT NULL CHECK (score >= 0 AND score <= 100),
    stage_times TEXT NOT NULL,
    steps INTEGER NOT NULL,
    wall_time_s REAL NOT NULL,
    failure_reason TEXT,
    video_path TEXT,
    success_terms TEXT NOT NULL DEFAULT '{{}}',
    counters TEXT NOT NULL DEFAULT '{{}}',
    backend TEXT NOT NULL DEFAULT '',
    finished_at TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now')),
    PRIMARY KEY (run_id, plan_hash, eval_seed, episode)
);
INSERT OR IGNORE INTO meta (key, value) VALUES ('schema_version', '{SCHEMA_VERSION}');
"""


class StoreError(Exception):
    """The store cannot be opened or used as asked (missing file, not a RoboDojo store, conflicting run)."""


def resolve_store_path(run: str | Path) -> Path:
    """Map what a user names on the command line (a .sqlite file or a run folder) to the store file."""
    path = Path(run)
    if path.is_dir():
        path = path / STORE_FILENAME
    if not path.is_file():
        raise StoreError(
            f"no results store at {str(run)!r}: expected a .sqlite file or a run folder containing {STORE_FILENAME}"
        )
    return path


def store_paths(source: str | Path) -> list[Path]:
    """What a report reads for one command-line source: a .sqlite file, a run folder, or a folder of runs (every
    store below it, e.g. `outputs/<suite>/<policy>` after a sweep, one store per run key), in a stable order."""
    path = Path(source)
    if path.is_dir() and not (path / STORE_FILENAME).is_file():
        found = sorted(path.rglob(STORE_FILENAME))
        if found:
            return found
        raise StoreError(f"no results store in {str(source)!r} or below it: expected a .sqlite file, a run folder "
                         f"containing {STORE_FILENAME}, or a folder of run folders")
    return [resolve_store_path(path)]


class ResultsStore:
    """A results store file, opened for writing (a run) or read-only (reports, live readers).

    A writer creates the file and its schema if needed. A read-only store never creates or changes the
    database and sees only committed episodes. Use one instance per thread (sqlite3 connections are not shared).
    """

    def __init__(self, path: str | Path, *, readonly: bool = False, busy_timeout_s: float = 30.0) -> None:
        self.path = Path(path)
        self.readonly = readonly
        try:
            if readonly:
                if not self.path.is_file():
                    raise StoreError(f"no results store at {str(self.path)!r}")
                self._db = sqlite3.connect(
                    f"{self.path.resolve().as_uri()}?mode=ro", uri=True, timeout=busy_timeout_s,
                    isolation_level=None,
                )
            else:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                self._db = sqlite3.connect(self.path, timeout=busy_timeout_s, isolation_level=None)
                tables = {r[0] for r in self._db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
                if tables and "meta" not in tables:  # never add our tables to someone else's database
                    raise StoreError(f"{str(self.path)!r} is an SQLite file but not a RoboDojo results store")
                self._db.execute("PRAGMA journal_mode=WAL")
                self._db.execute("PRAGMA synchronous=FULL")
                self._db.executescript(_SCHEMA)
            self._check_schema()
        except (sqlite3.DatabaseError, StoreError) as exc:
            if hasattr(self, "_db"):
                self._db.close()
            if isinstance(exc, StoreError):
                raise
            raise StoreError(f"{str(self.path)!r} is not a usable RoboDojo results store: {exc}") from exc

    def _check_schema(self) -> None:
        try:
            row = self._db.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
        except sqlite3.OperationalError as exc:
            raise StoreError(f"{str(self.path)!r} is an SQLite file but not a RoboDojo results store") from exc
        version = None if row is None else int(row[0])
        while version in _MIGRATIONS and not self.readonly:
            with self._transaction():  # read again under the write lock: another writer may have migrated
                version = int(self._db.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()[0])
                if version in _MIGRATIONS:
                    self._db.execute(_MIGRATIONS[version])
                    self._db.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (str(version + 1),))
                    version += 1
        if version != SCHEMA_VERSION and version not in _LEGACY_COLUMNS:
            raise StoreError(f"{str(self.path)!r} has results schema {version}, this version reads {SCHEMA_VERSION}")
        self._select = ", ".join(_LEGACY_COLUMNS.get(version, {}).get(c, c) for c in _COLUMNS)

    # -- runs ---------------------------------------------------------------------------------------------

    def ensure_run(self, run_id: str, meta: dict[str, Any]) -> bool:
        """Register a run with its metadata (suite, plan set hash, command...). Returns True if it is new.

        Resuming calls this again with the same metadata; different metadata for an existing run id means the
        command is not the one that started the run, and resuming it would mix two evaluations, so it raises.
        """
        encoded = json.dumps(meta, sort_keys=True)
        with self._transaction():
            row = self._db.execute("SELECT meta FROM runs WHERE run_id = ?", (run_id,)).fetchone()
            if row is None:
                self._db.execute("INSERT INTO runs (run_id, meta) VALUES (?, ?)", (run_id, encoded))
                return True
        if row[0] != encoded:
            raise StoreError(
                f"run {run_id!r} already exists in {str(self.path)!r} with different settings; "
                f"stored {row[0]}, given {encoded}"
            )
        return False

    def run_meta(self, run_id: str) -> dict[str, Any] | None:
        row = self._db.execute("SELECT meta FROM runs WHERE run_id = ?", (run_id,)).fetchone()
        return None if row is None else json.loads(row[0])

    def run_ids(self) -> list[str]:
        """Every run with a registered entry or at least one episode, oldest first."""
        rows = self._db.execute(
            "SELECT run_id FROM (SELECT run_id, created_at AS t FROM runs UNION ALL "
            "SELECT run_id, MIN(finished_at) AS t FROM episodes GROUP BY run_id) "
            "GROUP BY run_id ORDER BY MIN(t), run_id"
        ).fetchall()
        return [r[0] for r in rows]

    # -- episodes -----------------------------------------------------------------------------------------

    def add(self, result: EpisodeResult) -> bool:
        """Record one finished episode durably. Returns False (and keeps the stored row) if its key exists."""
        return self.add_many([result]) == 1

    def add_many(self, results: Sequence[EpisodeResult]) -> int:
        """Record the episodes that finished together (one batched tick) in one durable transaction: all or
        none of them survive a crash, at the cost of one disk sync instead of one per episode. Returns how many
        were new; existing keys keep their stored rows. Rows that share a value (a run's policy metadata is one
        dict for all of its episodes) have it encoded once: thousands of episodes can end in one tick."""
        encoded: dict[int, str] = {}  # id -> JSON, for objects `results` keeps alive throughout

        def as_json(value: Any) -> str:
            text = encoded.get(id(value))
            if text is None:
                text = encoded[id(value)] = json.dumps(value, sort_keys=True)
            return text

        rows = [[as_json(getattr(r, c)) if c in _JSON_COLUMNS else getattr(r, c) for c in _COLUMNS] for r in results]
        for values in rows:
            values[_SUCCESS] = int(values[_SUCCESS])
        with self._transaction():
            return self._db.executemany(_INSERT, rows).rowcount

    def finished(self, run_id: str) -> set[EpisodeKey]:
        """The keys of the episodes of `run_id` that are already recorded: what a resumed run must skip."""
        rows = self._db.execute(
            "SELECT plan_hash, eval_seed, episode FROM episodes WHERE run_id = ?", (run_id,)
        ).fetchall()
        return {EpisodeKey(*r) for r in rows}

    def count(self, run_id: str | None = None) -> int:
        if run_id is None:
            return self._db.execute("SELECT COUNT(*) FROM episodes").fetchone()[0]
        return self._db.execute("SELECT COUNT(*) FROM episodes WHERE run_id = ?", (run_id,)).fetchone()[0]

    def rows(self, run_id: str | None = None) -> list[EpisodeResult]:
        """Stored episodes (of one run, or all), in a stable order independent of when they finished."""
        where, params = ("WHERE run_id = ?", (run_id,)) if run_id is not None else ("", ())
        cur = self._db.execute(
            f"SELECT {self._select} FROM episodes {where} "
            "ORDER BY run_id, split, task, eval_seed, episode, plan_hash",
            params,
        )
        results = []
        for values in cur:
            record = dict(zip(_COLUMNS, values, strict=True))
            for column in _JSON_COLUMNS:
                record[column] = json.loads(record[column])
            record["success"] = bool(record["success"])
            results.append(EpisodeResult(**record))
        return results

    # -- plumbing -----------------------------------------------------------------------------------------

    def _transaction(self) -> _Transaction:
        if self.readonly:
            raise StoreError(f"{str(self.path)!r} was opened read-only")
        return _Transaction(self._db)

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> ResultsStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _Transaction:
    """BEGIN IMMEDIATE ... COMMIT (or ROLLBACK on error): takes the write lock up front so that two writers
    wait for each other instead of failing halfway through a read-then-write."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self._db = db

    def __enter__(self) -> None:
        self._db.execute("BEGIN IMMEDIATE")

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self._db.execute("COMMIT" if exc_type is None else "ROLLBACK")

