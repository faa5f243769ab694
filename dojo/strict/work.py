"""The simulated half of `dojo validate --strict`: every plan compiled twice and held at rest, and the policies'
episodes on them, spread over spawned worker processes, every result kept by plan hash.

A plan's hash covers all its inputs (spec and asset files, compiler and MuJoCo versions, setting, seed), but a
result also depends on the code that ran it (an expert's skills, the backend), so each record is kept under the
plan hash *and* a fingerprint of the dojo package's source (`code_fingerprint`): a re-run after fixing one task's
spec finds the other tasks' results and redoes only what the fix changed, and a re-run after changing a skill
redoes everything rather than judge the new code by the old code's episodes. Results are small JSON files beside
the plans, `<cache>/results/<hash>.json`, written by the parent process only (workers return them).

Workers are spawned, never forked (the parent may run a live progress display's thread), and get the spec
library and the pack folders once, through the pool's initializer.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from dojo.compiler.plan import Plan, compile_plan
from dojo.compiler.scene_sample import LayoutError
from dojo.compiler.spec_errors import SpecError
from dojo.compiler.spec_library import SpecLibrary

REST_SECONDS = 1.0
"""How long a compiled scene is simulated from its initial state, the robot holding home, to see it is at rest."""

PlanJob = tuple[str, str, str, int, str, str]
"""(task id, task's package, setting, scene seed, plan file, plan hash as the parent process computed it)."""
EpisodeJob = tuple[str, str]
"""(policy name: expert, zero or random; plan file)."""


@dataclass(frozen=True)
class PlanRecord:
    """One (task, setting, seed) compiled twice. `error` is set when it did not compile (`layout` is True when
    no layout settled, the stability check's business); otherwise `differs` names the plan fields that came out
    different the second time (or differ from the plan already on disk), `redraws` the layouts the compiler
    rejected, and `drift_mm` how far the farthest object moved in REST_SECONDS from the initial state."""

    setting: str
    seed: int
    hash: str
    path: str
    error: str | None = None
    layout: bool = False
    differs: tuple[str, ...] = ()
    redraws: int = 0
    drift_mm: float = 0.0
    drift_object: str | None = None
    horizon: int = 0
    seconds: float = 0.0


@dataclass(frozen=True)
class EpisodeRecord:
    """One policy's episode on one plan."""

    policy: str
    setting: str
    seed: int
    success: bool
    score: float
    steps: int
    seconds: float = 0.0
    error: str | None = None
    """Why the episode stopped early (the expert raised, say); it then counts as a failure."""


# ---- in a worker ----------------------------------------------------------------------------------------------

_STATE: dict[str, Any] = {}


def _init_worker(library: SpecLibrary, packs: list[str]) -> None:
    _STATE.clear()
    _STATE.update(library=library, packs=packs)


def compile_twice(job: PlanJob) -> PlanRecord:
    """Compile one plan twice, and hold it at rest. Its hash is also compared with the one the parent process
    computed, and the plan with the copy on disk when an earlier run left one: hash seeds, and so set orders,
    differ between processes."""
    task_id, package, setting, seed, path, expected = job
    library: SpecLibrary = _STATE["library"]
    task = library.get("task", task_id, package=package)
    start = time.monotonic()
    base = {"setting": setting, "seed": seed, "path": path, "hash": expected}
    try:
        first = compile_plan(library, task, setting, seed)
    except LayoutError as err:
        return PlanRecord(**base, error=str(err), layout=True, seconds=time.monotonic() - start)
    except SpecError as err:
        return PlanRecord(**base, error=str(err), seconds=time.monotonic() - start)
    except Exception as err:  # noqa: BLE001 - a contributed spec that breaks the compiler is reported, not raised
        return PlanRecord(**base, error=f"{type(err).__name__}: {err}", seconds=time.monotonic() - start)
    second = compile_plan(library, task, setting, seed)
    differs = _differences(first.to_json(), second.to_json())
    if first.hash != expected:
        differs += ("hash (against the parent process's)",)
    target = Path(path)
    if target.exists():
        differs += tuple(f"{key} (against the plan on disk)" for key in
                         _differences(first.to_json(), Plan.load(target).to_json()) if key not in differs)
    else:
        first.save(target)
    drift, moved = _drift(first)
    return PlanRecord(**base, differs=differs, redraws=int(first.settle.get("redraws", 0)),
                      drift_mm=round(drift * 1000.0, 3), drift_object=moved, horizon=first.horizon,
                      seconds=time.monotonic() - start)


def _differences(a: dict[str, Any], b: dict[str, Any]) -> tuple[str, ...]:
    return tuple(key for key in a if a[key] != b.get(key))


def _drift(plan: Plan) -> tuple[float, str | None]:
    """The largest displacement (m) of a movable object over REST_SECONDS from the plan's initial state, with the
    robot's controls held at their initial values, and which object it was."""
    model = plan.model()
    data = plan.initial_data(model)
    bodies = {name: model.body(obj["body"]).id for name, obj in plan.objects.items() if obj.get("free_joint")}
    start = {name: data.xpos[b].copy() for name, b in bodies.items()}
    mujoco.mj_step(model, data, nstep=max(1, round(REST_SECONDS / model.opt.timestep)))
    moved = {name: float(np.linalg.norm(data.xpos[b] - start[name])) for name, b in bodies.items()}
    if not moved:
        return 0.0, None
    name = max(moved, key=lambda n: moved[n])
    return moved[name], name


def run_episode(job: EpisodeJob) -> EpisodeRecord:
    """One episode of one reference policy on one plan, alone in its backend on one thread (CPU episodes do not
    depend on their batch neighbours, and the random policy is seeded by the scene seed: the figures do not
    depend on -j)."""
    from xpolicylab.policies import RandomPolicy, ZeroPolicy

    from dojo.experts.validity import run_policy
    from dojo.experts.oracle import OraclePolicy

    name, path = job
    plan = Plan.load(Path(path))
    if name == "expert":  # one per episode: it keeps every plan it has seen (the built-in specs stay cached)
        model = OraclePolicy({"packs": _STATE["packs"]})
    elif name == "zero":
        model = ZeroPolicy({"chunk_size": 8})
    else:
        model = RandomPolicy({"chunk_size": 8, "seed": plan.seed})
    start = time.monotonic()
    try:
        outcome = run_policy(model, [Path(path)], num_envs=1, threads=1)[0]
    except Exception as err:  # noqa: BLE001 - a contributed expert that breaks is a failed episode, named
        return EpisodeRecord(name, plan.setting, plan.seed, False, 0.0, 0, time.monotonic() - start,
                             f"{type(err).__name__}: {err}")
    return EpisodeRecord(name, plan.setting, plan.seed, outcome.success, outcome.score, outcome.steps,
                         time.monotonic() - start)


# ---- in the parent --------------------------------------------------------------------------------------------


def code_fingerprint(package: Path = Path(__file__).resolve().parents[1]) -> str:
    """A digest of every Python source file of the dojo package (paths and contents): what ran the episodes."""
    digest = hashlib.sha256()
    for file in sorted(package.rglob("*.py")):
        digest.update(file.relative_to(package).as_posix().encode() + b"\0" + file.read_bytes() + b"\0")
    return digest.hexdigest()[:16]


class ResultCache:
    """Records by plan hash and code: `<root>/<hash>.json` maps `<key>@<code>` (key: `plan`, or a policy name;
    code: `code_fingerprint()` unless given) to a record."""

    def __init__(self, root: Path, code: str | None = None) -> None:
        self.root = root
        self.code = code or code_fingerprint()

    def _file(self, digest: str) -> Path:
        return self.root / f"{digest}.json"

    def get(self, digest: str, key: str) -> dict[str, Any] | None:
        file = self._file(digest)
        if not file.exists():
            return None
        return json.loads(file.read_text()).get(f"{key}@{self.code}")

    def put(self, digest: str, key: str, record: Any) -> None:
        file = self._file(digest)
        data = json.loads(file.read_text()) if file.exists() else {}
        data = {k: v for k, v in data.items() if k.split("@")[0] != key}  # other code's record of this key
        data[f"{key}@{self.code}"] = asdict(record)
        file.parent.mkdir(parents=True, exist_ok=True)
        tmp = file.with_suffix(".tmp")
        tmp.write_text(json.dumps(data, sort_keys=True))
        tmp.replace(file)


class WorkerPool:
    """`jobs` spawned workers (or this process with one job) that hold the library and the packs."""

    def __init__(self, library: SpecLibrary, packs: Sequence[Path], jobs: int) -> None:
        self.jobs = max(1, jobs)
        self.args = (library, [str(p) for p in packs])
        self._pool: ProcessPoolExecutor | None = None

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any],
            done: Callable[[int, Any], None]) -> None:
        """Run `fn` on every item; `done(index, result)` is called in this process as each one finishes."""
        if self.jobs == 1 or len(items) == 1:
            _init_worker(*self.args)
            for i, item in enumerate(items):
                done(i, fn(item))
            return
        if self._pool is None:
            self._pool = ProcessPoolExecutor(self.jobs, mp_context=multiprocessing.get_context("spawn"),
                                             initializer=_init_worker, initargs=self.args)
        futures = {self._pool.submit(fn, item): i for i, item in enumerate(items)}
        for future in as_completed(futures):
            done(futures[future], future.result())

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def __enter__(self) -> "WorkerPool":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def run_cached(pool: WorkerPool, cache: ResultCache, fn: Callable[[Any], Any],
               jobs: Sequence[tuple[str, str, Any]], record_type: type, progress: Callable[[int], None]) -> list[Any]:
    """Each job is (plan hash, cache key, worker argument). Returns its records in job order: the cached one
    where there is one, else the worker's (then cached). `progress(n)` counts jobs as they finish."""
    records: dict[int, Any] = {}
    todo: list[int] = []
    for i, (digest, key, _) in enumerate(jobs):
        found = cache.get(digest, key)
        record = _record(record_type, found) if found is not None and _still_there(found) else None
        if record is None:
            todo.append(i)
        else:
            records[i] = record
    progress(len(records))

    def finished(k: int, record: Any) -> None:
        i = todo[k]
        records[i] = record
        cache.put(jobs[i][0], jobs[i][1], record)
        progress(1)

    pool.map(fn, [jobs[i][2] for i in todo], finished)
    return [records[i] for i in range(len(jobs))]


def _record(record_type: type, found: dict[str, Any]) -> Any:
    """A cached record as its type, or None when it was written by a version with other fields (then redone)."""
    try:
        return record_type(**{k: tuple(v) if isinstance(v, list) else v for k, v in found.items()})
    except TypeError:
        return None


def _still_there(record: dict[str, Any]) -> bool:
    """A plan's record is reused only while its plan file is there (the episodes load it)."""
    return "path" not in record or record.get("error") is not None or Path(record["path"]).exists()
