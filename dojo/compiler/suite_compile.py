"""Compiling a suite: the protocol's episode list, then one cached plan per episode, and `index.json`.

The episode list follows RoboDojo's protocol: N episodes per task (the suite's `episodes`, 50 by default),
Generalization tasks split between the standard and random settings (25 + 25 by default), every other task in
the standard setting, repeated for each evaluation seed. Scene seeds are `eval_seed * 10000 + index`, so the
episodes of seed 0 are the same whatever other seeds are evaluated.

Plans are stored as `<out>/<task>/<setting>-<scene seed>-<hash16>.json`; a plan whose file already exists is not
rebuilt, since its name carries the hash of all its inputs.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import time
from collections.abc import Collection, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

from dojo.compiler.episodes import Episode, PlannedEpisode
from dojo.compiler.plan import compile_plan, compiler_id, plan_hash
from dojo.compiler.spec_errors import did_you_mean
from dojo.compiler.spec_library import Spec, SpecLibrary
from dojo.compiler.taxonomy import taxonomy_of

SEED_STRIDE = 10_000
INDEX_FORMAT = "robodojo-plan-index/1"


def suite_episodes(library: SpecLibrary, suite: Spec, *, seeds: list[int] | None = None,
                   episodes: int | None = None, tasks: Collection[str] | None = None) -> list[Episode]:
    """The suite's episodes, in a stable order (task, seed, setting, index); only those of `tasks` when given
    (each must be one of the suite's tasks)."""
    seeds = list(seeds if seeds is not None else suite.data.get("seeds", [0]))
    standard_share = suite.data.get("generalization_split", {}).get("standard", 0.5)
    entries = library.suite_tasks(suite)
    if tasks is not None:
        ids = [task.id for task, _ in entries]
        for wanted in tasks:
            if wanted not in ids:
                raise KeyError(f"suite {suite.id} has no task '{wanted}'{did_you_mean(str(wanted), ids)}; "
                               f"its tasks: {', '.join(ids)}")
        entries = [(task, entry) for task, entry in entries if task.id in set(tasks)]
    taxonomy = taxonomy_of(library)
    out = []
    for task, entry in entries:
        count = int(episodes or entry.get("episodes") or suite.data.get("episodes", 50))
        dimension = task.data["dimension"]
        compared = taxonomy.compare_settings(dimension)  # RoboDojo's Generalization: standard and random
        if compared:
            n_first = round(count * standard_share)
            split = [(compared[0], n_first), (compared[1], count - n_first)]
        else:
            split = [("standard", count)]
        for eval_seed in seeds:
            for setting, n in split:
                out += [Episode(task.id, dimension, setting, eval_seed * SEED_STRIDE + i, eval_seed, i)
                        for i in range(n)]
    return out


def plan_path(out: Path, episode: Episode, digest: str) -> Path:
    return out / episode.task / f"{episode.setting}-{episode.scene_seed}-{digest[:16]}.json"


PlanJob = tuple[str, str, str, int, str]
"""One plan to compile: (task id, task's package, setting, scene seed, plan file)."""

# What a worker process compiles from, given once per worker by the pool's initializer.
_WORKER_STATE: tuple[SpecLibrary, dict[str, list[int]]] | None = None


def _init_worker(library: SpecLibrary, demos: dict[str, list[int]]) -> None:
    global _WORKER_STATE
    _WORKER_STATE = (library, demos)


def _compile_one(job: PlanJob) -> str:
    task_id, package, setting, seed, path = job
    assert _WORKER_STATE is not None
    library, demos = _WORKER_STATE
    task = library.get("task", task_id, package=package)
    compile_plan(library, task, setting, seed, demo_lengths=demos.get(task_id)).save(Path(path))
    return path


PLANS_PER_WORKER = 32
"""Under `jobs=auto`, a worker process is started for every this many plans at most: a spawned worker spends
seconds importing the compiler before its first plan, and a plan takes 45-100 ms (insert_tubes: 78 ms on the
2-core CI machine, 47 ms on a 16-core GPU host), so fewer plans than this each would not repay the start."""


def worker_count(jobs: int | str, plans: int) -> int:
    """Processes for compiling `plans` plans: `jobs` as given, or for `auto` one per CPU this process may use,
    no more than one per `PLANS_PER_WORKER` plans (1: compile in this process)."""
    if jobs == "auto":
        cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        return max(1, min(cpus, plans // PLANS_PER_WORKER))
    try:
        count = int(jobs)
    except (TypeError, ValueError):
        raise ValueError(f"jobs={jobs!r}: a number of processes, or auto") from None
    if count < 1:
        raise ValueError(f"jobs={count}: at least 1 process (or auto)")
    return count


def compile_plan_files(library: SpecLibrary, todo: Sequence[PlanJob], *, jobs: int | str = 1,
                       demo_lengths: dict[str, list[int]] | None = None,
                       progress: Callable[[int, int], None] | None = None) -> None:
    """Compile and save each job's plan, in worker processes (`worker_count(jobs, ...)`) when there is more than
    one plan.

    Workers are spawned, never forked: the calling process may already run threads (JAX's runtime once an mjx
    backend or benchmark started, MuJoCo's thread pools, a live progress display), and a forked copy of a
    multithreaded process can deadlock on a lock some thread held. The library travels to each worker once."""
    demos = demo_lengths or {}
    done = 0
    jobs = worker_count(jobs, len(todo))
    if jobs > 1 and len(todo) > 1:
        with ProcessPoolExecutor(max_workers=min(jobs, len(todo)), mp_context=multiprocessing.get_context("spawn"),
                                 initializer=_init_worker, initargs=(library, demos)) as pool:
            for _ in pool.map(_compile_one, todo, chunksize=max(1, len(todo) // (4 * jobs))):
                done += 1
                if progress:
                    progress(done, len(todo))
        return
    _init_worker(library, demos)
    for job in todo:
        _compile_one(job)
        done += 1
        if progress:
            progress(done, len(todo))


@dataclass
class CompileStats:
    plans: int
    compiled: int
    cached: int
    index: str
    episodes: tuple[PlannedEpisode, ...] = ()
    seconds: float = 0.0
    replaced_compiler: str | None = None
    """The compiler whose plans the folder's index listed before, where another than this one (`compiler_id`)."""

    def summary(self, label: str) -> str:
        """What was compiled and what reused, for the console."""
        each = f", {1000 * self.seconds / self.compiled:.0f} ms each" if self.compiled else ""
        return (f"{label}: {self.plans} plans ({self.compiled} compiled in {self.seconds:.1f} s{each}; "
                f"{self.cached} reused) -> {self.index}")

    def compiler_note(self) -> str | None:
        """Why plans that were in the folder were compiled again, where they were: a plan's name carries the
        compiler that made it (`plan_hash` hashes `compiler_id`, MuJoCo's version included), so a folder compiled
        by another install serves none of its plans here; nor do kernels compiled ahead for its buckets
        (`dojo bench kernels`), and the new plans may bucket otherwise. Found on an H200 (2026-12-03): a folder
        compiled with MuJoCo 4.0.1 was compiled again, silently, by a GPU host with 4.0.0."""
        if self.replaced_compiler is None or not self.compiled:
            return None
        return (f"{self.compiled} plans compiled again: {Path(self.index).parent} held plans of "
                f"'{self.replaced_compiler}', this is '{compiler_id()}' (a plan is named by what compiled it; "
                "plans and kernels compiled ahead carry over only between installs with the same versions)")


def plan_files(folder: Path) -> list[Path]:
    """The plan files of `folder`: where `compile_suite` wrote it (`index.json` beside one folder per task), each
    distinct plan of its episodes in the protocol's order, so that a bench runs the suite's own workload (the
    random setting's scenes, the per-episode objects); else every `*.json` file in it, by name."""
    index = folder / "index.json"
    if not index.is_file():
        return sorted(folder.glob("*.json"))
    paths = [folder / entry["path"] for entry in json.loads(index.read_text())["plans"]]
    return list(dict.fromkeys(paths))


def compile_suite(library: SpecLibrary, suite: Spec, out: Path, *, jobs: int | str = 1, seeds: list[int] | None = None,
                  episodes: int | None = None, demo_lengths: dict[str, list[int]] | None = None,
                  tasks: Collection[str] | None = None, progress: Callable[[int, int], None] | None = None,
                  split: str = "public") -> CompileStats:
    """Compile every episode's plan into `out` (reusing existing ones) and write `out/index.json`; the stats
    carry the episodes, typed, in protocol order, for the evaluation loop (the index is for people and tools).
    `demo_lengths` (task id -> lengths, from `dojo collect`) set the tasks' `auto` horizons; `tasks` keeps only
    those of the suite's tasks; `split` is the one the episodes are scored in."""
    started = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    index = out / "index.json"
    before = index_compiler(out)
    entries, planned, todo, queued = [], [], [], set()
    demos = demo_lengths or {}
    specs = {task.id: task for task, _ in library.suite_tasks(suite)}
    for episode in suite_episodes(library, suite, seeds=seeds, episodes=episodes, tasks=tasks):
        task = specs[episode.task]
        digest = plan_hash(library, task, episode.setting, episode.scene_seed, demos.get(episode.task))
        path = plan_path(out, episode, digest)
        entries.append({**asdict(episode), "hash": digest, "path": str(path.relative_to(out))})
        planned.append(PlannedEpisode(**asdict(episode), plan_hash=digest, plan_path=path, split=split))
        if not path.exists() and path not in queued:
            queued.add(path)
            todo.append((task.id, task.package, episode.setting, episode.scene_seed, str(path)))
    compile_plan_files(library, todo, jobs=jobs, demo_lengths=demos, progress=progress)
    tmp = index.with_suffix(".tmp")
    tmp.write_text(json.dumps({"format": INDEX_FORMAT, "suite": suite.id, "compiler": compiler_id(),
                               "plans": entries}, indent=1))
    os.replace(tmp, index)
    return CompileStats(plans=len(entries), compiled=len(todo), cached=len(entries) - len(todo), index=str(index),
                        episodes=tuple(planned), seconds=time.perf_counter() - started,
                        replaced_compiler=before if before != compiler_id() else None)


def index_compiler(folder: Path) -> str | None:
    """The compiler (`compiler_id`) that the plan index in `folder` names, None without a readable one (the index
    is this tool's own file, rewritten by every compile: one that does not parse is replaced, not reported)."""
    try:
        found = json.loads((folder / "index.json").read_text()).get("compiler")
    except (OSError, ValueError, AttributeError):
        return None
    return found if isinstance(found, str) else None
