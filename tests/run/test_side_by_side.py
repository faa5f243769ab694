"""A run's routes side by side (`dojo.evaluation.side_by_side`): real loops on the CPU backend, on threads of their
own, each with its own results-store connection to one SQLite file; every episode recorded once; the first failure
or an interrupt stops every loop at its next step and is raised once all have ended; a resumed run runs exactly what
is missing."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from dojo.backends.registry import BackendOptions, make_backend
from dojo.compiler.spec_library import SpecLibrary
from dojo.compiler.suite_compile import compile_suite
from dojo.evaluation.evaluate import Stopped, evaluate
from dojo.evaluation.policy_link import open_policy
from dojo.evaluation.progress import Progress
from dojo.evaluation.results_store import ResultsStore
from dojo.evaluation.side_by_side import SharedProgress, run_side_by_side

PACK = Path(__file__).resolve().parents[1] / "recording" / "pack"


@pytest.fixture(scope="module")
def queue(tmp_path_factory):
    library = SpecLibrary.load([PACK], strict=False)
    plans = tmp_path_factory.mktemp("plans")
    return list(compile_suite(library, library.get("suite", "short_suite"), plans, episodes=4).episodes)


def _route(episodes, store_path: Path, progress, built: list[str] | None = None, hold: bool = False):
    """A route as `dojo run` makes one: the CPU backend, the zero policy, a store connection of its own. `built`
    collects the thread each backend was built on; with `hold`, the backend is built only once the run is told to
    stop (so the loop's first step finds the stop)."""

    def run(stop: threading.Event) -> int:
        def factory():
            if hold:
                assert stop.wait(30), "the run was never told to stop"
            if built is not None:
                built.append(threading.current_thread().name)
            return make_backend("mujoco", BackendOptions(settings={"threads": 1}, action_modes=("joint",)))

        link = open_policy({"name": "zero", "url": None, "chunk_size": 4}, "arx_x5_bimanual")
        try:
            with ResultsStore(store_path) as store:
                return evaluate(episodes, factory, link, store, "run", num_envs=2, progress=progress, stop=stop)
        finally:
            link.close()

    return run


def _recorded(store_path: Path) -> list[tuple]:
    with ResultsStore(store_path) as store:
        return sorted((r.plan_hash, r.eval_seed, r.episode) for r in store.rows("run"))


def test_routes_run_on_threads_of_their_own_and_every_episode_is_recorded_once(queue, tmp_path) -> None:
    store_path = tmp_path / "results.sqlite"
    with ResultsStore(store_path) as store:
        store.ensure_run("run", {})
    built: list[str] = []
    with Progress(len(queue), mode="quiet") as progress:
        shared = SharedProgress(progress)
        run_side_by_side([_route(queue[:2], store_path, shared, built), _route(queue[2:], store_path, shared, built)])
        assert progress.done == len(queue)
    assert sorted(built) == ["MainThread", "dojo-route-1"]
    assert _recorded(store_path) == sorted((e.plan_hash, e.eval_seed, e.episode) for e in queue)


def test_a_failing_route_stops_the_others_and_a_resumed_run_runs_only_what_is_missing(queue, tmp_path) -> None:
    store_path = tmp_path / "results.sqlite"
    with ResultsStore(store_path) as store:
        store.ensure_run("run", {})

    def broken(stop: threading.Event) -> None:
        raise ConnectionError("the policy server went away")

    with Progress(len(queue), mode="quiet") as progress:
        shared = SharedProgress(progress)
        with pytest.raises(ConnectionError, match="went away"):
            run_side_by_side([_route(queue, store_path, shared, hold=True), broken])
    assert not [t for t in threading.enumerate() if t.name.startswith("dojo-route-")]
    assert _recorded(store_path) == []  # stopped at its first step: nothing half recorded
    with Progress(len(queue), mode="quiet") as progress:
        assert _route(queue, store_path, progress)(threading.Event()) == len(queue)
    assert _recorded(store_path) == sorted((e.plan_hash, e.eval_seed, e.episode) for e in queue)


def test_an_interrupt_on_the_first_route_stops_the_others_before_it_is_raised(queue, tmp_path) -> None:
    store_path = tmp_path / "results.sqlite"
    with ResultsStore(store_path) as store:
        store.ensure_run("run", {})
    ended: list[str] = []

    def interrupted(stop: threading.Event) -> None:
        raise KeyboardInterrupt

    def other(stop: threading.Event) -> None:
        try:
            _route(queue, store_path, Progress(len(queue), mode="quiet"), hold=True)(stop)
        except Stopped:
            ended.append("stopped")
            raise

    with pytest.raises(KeyboardInterrupt):
        run_side_by_side([interrupted, other])
    assert ended == ["stopped"] and _recorded(store_path) == []


ZERO = {"name": "zero", "url": None, "chunk_size": 4}


def _job(queue, store_path: Path, policy: dict | None = None):
    """The second of two CPU routes as `dojo run` hands one to its own process."""
    from functools import partial

    from dojo.cli.run_cmd import _evaluate_route_apart

    routes = [({"name": "mujoco", "threads": 1}, queue[:2]), ({"name": "mujoco", "threads": 1}, queue[2:])]
    meta = open_policy(ZERO, "arx_x5_bimanual").metadata
    return partial(_evaluate_route_apart, routes, 1, policy_cfg=policy or ZERO, embodiment="arx_x5_bimanual",
                   store_path=store_path, run_id="run", num_envs=2, rendering=(meta, (), (640, 480)), timeout=None,
                   recorder_factory=None, on_device="off")


def test_a_route_in_a_process_of_its_own_records_its_episodes_and_the_run_sees_them(queue, tmp_path) -> None:
    from dojo.evaluation.side_by_side import run_in_process

    store_path = tmp_path / "results.sqlite"
    with ResultsStore(store_path) as store:
        store.ensure_run("run", {})
    with Progress(len(queue), mode="quiet") as progress:
        assert run_in_process(_job(queue, store_path), progress, threading.Event()) == 2
        assert progress.done == 2 and progress.snapshot()["interactions"] > 0
    assert _recorded(store_path) == sorted((e.plan_hash, e.eval_seed, e.episode) for e in queue[2:])


def test_only_routes_with_episodes_left_run_so_a_resumed_run_spawns_no_process_for_a_finished_route(
        queue, tmp_path) -> None:
    from dojo.cli.run_cmd import routes_left

    routes = [({"name": "mjx"}, queue[:2]), ({"name": "mujoco"}, queue[2:])]
    keys = [(e.plan_hash, e.eval_seed, e.episode) for e in queue]
    store_path = tmp_path / "results.sqlite"
    with ResultsStore(store_path) as store:
        store.ensure_run("run", {})
        assert routes_left(routes, store.finished("run")) == [0, 1]
        with Progress(len(queue), mode="quiet") as progress:
            _route(queue[2:], store_path, progress)(threading.Event())  # the second route's episodes recorded
        assert routes_left(routes, store.finished("run")) == [0]
    assert routes_left(routes, set(keys[:3])) == [1]
    assert routes_left(routes, set(keys)) == []


def test_a_route_process_is_stopped_by_the_run_and_its_error_is_the_runs(queue, tmp_path) -> None:
    from dojo.evaluation.side_by_side import run_in_process

    store_path = tmp_path / "results.sqlite"
    with ResultsStore(store_path) as store:
        store.ensure_run("run", {})
    stop = threading.Event()
    stop.set()  # another route failed before this one's first step
    with pytest.raises(Stopped):
        run_in_process(_job(queue, store_path), Progress(len(queue), mode="quiet"), stop)
    assert _recorded(store_path) == []
    with pytest.raises(ValueError, match="no_such_policy"):
        run_in_process(_job(queue, store_path, {**ZERO, "name": "no_such_policy"}), Progress(4, mode="quiet"),
                       threading.Event())


SUITE = """kind: suite
version: 1
id: routed_pair
tasks: [short_test, probe_events]
episodes: 2
seeds: [0]
generalization_split: {standard: 1.0}
"""
"""A task the mjx backend runs and one it sends to the CPU reference backend (scripted events)."""


def _dojo_run(tmp: Path, pack: Path, routes: str) -> tuple[list[tuple], str]:
    import sqlite3
    import subprocess
    import sys

    results = tmp / f"{routes}.sqlite"
    cmd = [sys.executable, "-m", "dojo.cli.main", "run", f"packs=[{pack}]", "suite=routed_pair", "backend=mjx",
           "backend.impl=warp", "policy=zero", "num_envs=2", f"routes={routes}", f"results={results}",
           f"plans={tmp / 'plans'}", "progress=quiet", f"hydra.run.dir={tmp / f'out-{routes}'}"]
    done = subprocess.run(cmd, cwd=tmp, capture_output=True, text=True, timeout=3600)
    assert done.returncode == 0, done.stderr[-4000:]
    with sqlite3.connect(results) as db:
        rows = db.execute("SELECT task, backend, success, score, steps, eval_seed, episode FROM episodes "
                          "ORDER BY task, eval_seed, episode").fetchall()
    return rows, done.stderr


@pytest.mark.slow
def test_dojo_run_scores_the_same_with_its_routes_side_by_side_as_in_turn(tmp_path) -> None:
    """The user's command on the batched backend with a task it sends to the fallback: both loops run and close,
    and the rows are those of the routes one after the other."""
    import shutil

    pack = tmp_path / "pack"  # the two tasks with their assets in one pack (a pack names only its own specs)
    for source in (PACK, PACK.parents[1] / "backends" / "pack"):
        for kind in ("tasks", "assets"):
            shutil.copytree(source / kind, pack / kind, dirs_exist_ok=True)
    (pack / "suites").mkdir()
    (pack / "suites" / "routed_pair.yaml").write_text(SUITE)
    together, said = _dojo_run(tmp_path, pack, "side_by_side")
    assert "on backend mjx went" in said and "on backend mujoco went" in said
    assert {(task, backend) for task, backend, *_ in together} == {("short_test", "mjx"), ("probe_events", "mujoco")}
    assert together == _dojo_run(tmp_path, pack, "in_turn")[0]

