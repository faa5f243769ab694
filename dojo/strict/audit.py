"""Running the strict checks over packs: one row per task (and per pack), the checks in order, the simulated work
gathered only for the tasks still standing and only when a check first needs it.

Checks are run column by column: every row's schema check, then every row's safety check, and so on. A row stops
at its first failure (the rest of its checks are skipped, naming the one that failed), and the plans and episodes
a check needs are gathered for all surviving tasks at once, so the worker pool is busy with every task's seeds
together rather than one task at a time.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from dojo.compiler.pack_audit import pack_tasks, protocol_settings
from dojo.compiler.pack_limits import PackLimits
from dojo.compiler.plan import plan_hash
from dojo.compiler.spec_errors import display_path
from dojo.compiler.spec_library import SpecLibrary

from dojo.experts.validity import episode_list
from dojo.strict.checks import PACK_CHECKS, TASK_CHECKS, Audit, CheckResult, Context, has_expert
from dojo.strict.work import EpisodeRecord, PlanRecord, ResultCache, WorkerPool, compile_twice, run_cached, run_episode

STAGES = {"plans": "compiling plans twice, at rest", "expert": "expert episodes", "floor": "zero and random episodes"}
"""What each kind of work is called on the progress bar."""


class Gatherer:
    """Fills rows with plans and episodes, from the cache or the pool, showing progress."""

    def __init__(self, ctx: Context, pool: WorkerPool, cache: Path, progress: Progress) -> None:
        self.ctx, self.pool, self.progress = ctx, pool, progress
        self.plan_dir = cache / "plans"
        self.results = ResultCache(cache / "results")
        self.seconds: dict[tuple[str, str], float] = {}  # (row file, need) -> worker seconds spent on it

    def gather(self, need: str, rows: Sequence[Audit]) -> None:
        if need == "plans":
            self._plans(rows)
        else:
            self._episodes(rows, ("expert",) if need == "expert" else ("zero", "random"), need)

    def _bar(self, need: str, total: int) -> Callable[[int], None]:
        """A progress bar for one kind of work, as a function counting finished jobs; where the output is no
        terminal (a CI log), a line at every tenth instead."""
        bar = self.progress.add_task(STAGES[need], total=total)
        start, counts = time.monotonic(), {"done": 0, "shown": -1}

        def advance(n: int) -> None:
            self.progress.advance(bar, n)
            counts["done"] += n
            tenth = counts["done"] * 10 // max(total, 1)
            if self.progress.disable and tenth > counts["shown"]:
                counts["shown"] = tenth
                self.progress.console.print(f"{STAGES[need]}: {counts['done']}/{total} "
                                            f"({time.monotonic() - start:.0f} s)")
        return advance

    def _plans(self, rows: Sequence[Audit]) -> None:
        jobs, owners = [], []
        for row in rows:
            assert row.task is not None and row.task.spec is not None
            spec = row.task.spec
            for setting in protocol_settings(self.ctx.library, spec):
                for seed in range(self.ctx.seeds):
                    digest = plan_hash(self.ctx.library, spec, setting, seed)
                    path = self.plan_dir / spec.id / f"{setting}-{seed}-{digest[:16]}.json"
                    jobs.append((digest, "plan", (spec.id, spec.package, setting, seed, str(path), digest)))
                    owners.append(row)
        records = run_cached(self.pool, self.results, compile_twice, jobs, PlanRecord, self._bar("plans", len(jobs)))
        for row in rows:
            row.plans = [r for r, owner in zip(records, owners) if owner is row]
            self.seconds[(row.file, "plans")] = sum(r.seconds for r in row.plans)

    def _episodes(self, rows: Sequence[Audit], policies: tuple[str, ...], need: str) -> None:
        jobs, owners = [], []
        for row in rows:
            assert row.task is not None and row.plans is not None
            plans = {(p.setting, p.seed): p for p in row.plans}
            for setting, seed in episode_list(self.ctx.library, row.task.task_id, self.ctx.seeds):
                plan = plans[(setting, seed)]
                for policy in policies if has_expert(row) else [p for p in policies if p != "expert"]:
                    jobs.append((plan.hash, policy, (policy, plan.path)))
                    owners.append((row, policy))
        records = run_cached(self.pool, self.results, run_episode, jobs, EpisodeRecord, self._bar(need, len(jobs)))
        for row in rows:
            for policy in policies:
                row.episodes[policy] = [r for r, owner in zip(records, owners) if owner == (row, policy)]
            self.seconds[(row.file, need)] = sum(r.seconds for p in policies for r in row.episodes[p])


def rows_of(library: SpecLibrary, packs: Sequence[Path]) -> list[Audit]:
    """The report's rows: per pack, the pack itself, then its tasks in file order."""
    rows = []
    for pack in packs:
        rows.append(Audit(pack, "(pack)", display_path(pack)))
        rows += [Audit(pack, t.task_id, t.display, t) for t in pack_tasks(library, pack)]
    return rows


def audit_packs(library: SpecLibrary, packs: Sequence[Path], *, seeds: int, jobs: int, cache: Path,
                limits: PackLimits | None = None, console: Console | None = None) -> list[Audit]:
    """Run every check on every row of `packs` (loaded into `library`); returns the rows with their results."""
    ctx = Context(library, limits or PackLimits(), seeds)
    rows = rows_of(library, packs)
    for row in rows:
        if row.task is None:
            row.results = [_timed(check.run, row, ctx) for check in PACK_CHECKS]
    tasks = [row for row in rows if row.task is not None]
    console = console or Console(file=sys.stderr)
    progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                        console=console, transient=False, disable=not console.is_terminal)
    with WorkerPool(library, packs, jobs) as pool, progress:
        gatherer = Gatherer(ctx, pool, cache, progress)
        gathered: set[str] = set()
        for check in TASK_CHECKS:
            standing = [row for row in tasks if not row.failed]
            if check.needs and check.needs not in gathered and standing:
                gatherer.gather(check.needs, standing)
            for row in tasks:
                if row in standing:
                    result = _timed(check.run, row, ctx)
                    if check.needs and check.needs not in gathered:
                        result = _plus_seconds(result, gatherer.seconds.get((row.file, check.needs), 0.0))
                    row.results.append(result)
                else:
                    failed = next(r.check for r in row.results if r.status == "fail")
                    row.results.append(CheckResult(check.name, "skip", f"not run: {failed} failed"))
            if check.needs:
                gathered.add(check.needs)
    return rows


def _timed(run: Callable[[Audit, Context], CheckResult], row: Audit, ctx: Context) -> CheckResult:
    start = time.monotonic()
    result = run(row, ctx)
    return _plus_seconds(result, time.monotonic() - start)


def _plus_seconds(result: CheckResult, seconds: float) -> CheckResult:
    return CheckResult(result.check, result.status, result.figure, result.findings, result.seconds + seconds)
