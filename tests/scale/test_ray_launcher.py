"""`dojo run launcher=ray` on a real local Ray cluster of two CPUs (one for the module: Ray takes seconds to start):
two workers record exactly what one process records, episode by episode; `kill -9` of a worker mid-run loses and
repeats nothing; a run resumes across launchers; each worker talks to its own policy server when given a list.

The cluster is started here, as `ray start --head` would start one, and each `dojo run` joins it by address
(`launcher.address`), as a run joins a cluster that is already up.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from dojo.launch.ray_launcher import start_local_cluster
from dojo.evaluation.results_store import ResultsStore

ray = pytest.importorskip("ray", reason="the Ray launcher needs the ray extra: pip install 'robodojo[ray]'")

# Two short tasks of the default suite, two episodes each, by the privileged oracle: every episode succeeds, so
# success, score, steps and every stage's time are compared, not only failures at the horizon.
RUN = ["run", "tasks=[general_pickup,push_t]", "policy=oracle", "progress=jsonl"]
WORKER_TITLE = "ray::_ShardWorker"


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, str]]:
    """A two-CPU cluster owned by this process, and the environment in which `dojo run` joins it."""
    saved = dict(os.environ)
    start_local_cluster(num_cpus=2)  # as `dojo run launcher=ray` starts one
    # Ray enables token authentication for the cluster it starts (RAY_AUTH_MODE=token in this process); a driver
    # that joins by address must say so too.
    env = dict(os.environ, DOJO_PLAN_CACHE=str(tmp_path_factory.mktemp("plans")))
    env["DOJO_RAY_ADDRESS"] = ray.get_runtime_context().gcs_address
    try:
        yield env
    finally:
        ray.shutdown()
        os.environ.clear()
        os.environ.update(saved)


def dojo(args: list[str], env: dict[str, str], cwd: Path, background: bool = False
         ) -> subprocess.CompletedProcess | subprocess.Popen:
    cmd = [sys.executable, "-m", "dojo.cli.main", *args]
    if background:
        return subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)


def on_ray(env: dict[str, str], workers: int = 2) -> list[str]:
    return ["launcher=ray", f"launcher.address={env['DOJO_RAY_ADDRESS']}", f"launcher.workers={workers}"]


def episodes(path: Path) -> dict[tuple, tuple]:
    """What must not depend on where an episode ran, per (plan, eval seed, episode)."""
    with ResultsStore(path, readonly=True) as store:
        return {r.key: (r.success, r.score, r.steps, r.stage_times, r.failure_reason) for r in store.rows()}


@pytest.fixture(scope="module")
def reference(cluster: dict[str, str], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The same episodes in one process (launcher=local)."""
    tmp = tmp_path_factory.mktemp("local")
    done = dojo([*RUN, f"results={tmp / 'local.sqlite'}"], cluster, tmp)
    assert done.returncode == 0, done.stderr
    rows = episodes(tmp / "local.sqlite")
    assert len(rows) == 4 and all(success for success, *_ in rows.values())
    return tmp / "local.sqlite"


def test_the_workers_record_what_one_process_records(cluster: dict[str, str], reference: Path,
                                                     tmp_path: Path) -> None:
    """Three workers asked for on a cluster that holds two: the two run every episode, and the run ends without
    waiting for the third, which a fixed cluster never places."""
    done = dojo([*RUN, *on_ray(cluster, workers=3), "num_envs=1", f"results={tmp_path / 'ray.sqlite'}"], cluster,
                tmp_path)
    assert done.returncode == 0, done.stderr
    assert "ray: 3 workers asked for, 2 fit in a cluster of 2 CPU" in done.stderr
    assert episodes(tmp_path / "ray.sqlite") == episodes(reference)
    summary = next(line for line in done.stdout.splitlines() if line.startswith('{"event": "summary"'))
    assert '"done": 4, "total": 4' in summary  # the driver's progress counted every worker's episodes


def worker_pids() -> list[int]:
    """This test's cluster's evaluation workers: processes below this one (the cluster's head) with Ray's title."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(parent, []).append(int(entry.name))
    found, todo = [], [os.getpid()]
    while todo:
        for pid in children.get(todo.pop(), []):
            todo.append(pid)
            try:
                if (Path("/proc") / str(pid) / "cmdline").read_bytes().startswith(WORKER_TITLE.encode()):
                    found.append(pid)
            except OSError:
                continue
    return found


def test_kill_9_of_a_worker_mid_run_loses_and_repeats_nothing(cluster: dict[str, str], reference: Path,
                                                                tmp_path: Path) -> None:
    store = tmp_path / "killed.sqlite"
    proc = dojo([*RUN, *on_ray(cluster), "num_envs=1", f"results={store}"], cluster, tmp_path, background=True)
    count, deadline = 0, time.monotonic() + 300
    while count < 1 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
        if store.exists():
            try:
                with sqlite3.connect(f"file:{store}?mode=ro", uri=True) as db:
                    count = db.execute("SELECT COUNT(*) FROM episodes").fetchone()[0]
            except sqlite3.OperationalError:
                continue
    pids = worker_pids()
    assert proc.poll() is None and count < 4 and len(pids) == 2, "the run ended before a worker could be killed"
    os.kill(pids[0], signal.SIGKILL)
    out, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err
    requeued = re.search(r"worker \d died .*; (\d+) unfinished episodes re-queued", err)
    assert requeued and int(requeued.group(1)) >= 1, err  # the dead worker had an episode in flight
    assert episodes(store) == episodes(reference)  # every episode once, as one process records it


def test_a_run_resumes_across_launchers(cluster: dict[str, str], reference: Path, tmp_path: Path) -> None:
    store = tmp_path / "resumed.sqlite"
    shutil.copy(reference, store)
    with sqlite3.connect(store) as db:  # as if the local run had been killed after two episodes
        db.execute("DELETE FROM episodes WHERE rowid IN (SELECT rowid FROM episodes ORDER BY rowid DESC LIMIT 2)")
    done = dojo([*RUN, *on_ray(cluster, workers=1), f"results={store}"], cluster, tmp_path)
    assert done.returncode == 0, done.stderr
    summary = next(line for line in done.stdout.splitlines() if line.startswith('{"event": "summary"'))
    assert '"done": 4, "total": 4, "resumed": 2' in summary
    assert episodes(store) == episodes(reference)


def test_workers_talk_to_their_own_servers_and_share_one_by_disjoint_environment_ids(cluster: dict[str, str],
                                                                                   tmp_path: Path) -> None:
    """Three workers of one slot each and `policy.url` listing two servers: workers 0 and 2 talk to the first, worker
    1 to the second (round robin). Both serve a policy that keeps state per environment id (episode_keeper.py), so
    workers 0 and 2 must address the first by different ids, or their episodes run under one id and fail."""
    pack = Path(__file__).resolve().parents[1] / "specs" / "pack"
    ports = []
    for _ in range(2):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            ports.append(s.getsockname()[1])
    logs = [tmp_path / f"server{i}.log" for i in range(2)]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parent)}
    servers = [subprocess.Popen([sys.executable, "-m", "xpolicylab.serve", "policy=episode_keeper:EpisodeKeeper",
                                 f"port={port}"], stdout=subprocess.DEVNULL, stderr=log.open("w"), env=env)
               for port, log in zip(ports, logs)]
    try:
        urls = ",".join(f"ws://127.0.0.1:{port}" for port in ports)
        done = dojo(["run", f"packs=[{pack}]", "suite=mini_test", "episodes=2", "policy=remote", "num_envs=1",
                     f"policy.url=[{urls}]", *on_ray(cluster, workers=3), "launcher.cpus_per_worker=0.5",
                     f"results={tmp_path / 'r.sqlite'}"], cluster, tmp_path)
    finally:
        for server in servers:
            server.terminate()
            server.wait(timeout=30)
    assert done.returncode == 0, done.stderr
    reasons = [reason for *_, reason in episodes(tmp_path / "r.sqlite").values()]
    assert len(reasons) == 4 and not [r for r in reasons if r and r.startswith("policy_error")], reasons
    opened = [log.read_text().count("connection open") for log in logs]
    assert opened == [3, 1]  # the first: this run's own look at the policy, and workers 0 and 2; the second: 1
