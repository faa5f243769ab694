"""Parallel sweeps through Hydra's joblib launcher: `dojo run -m hydra/launcher=joblib policy.url=A,B` runs one job
per policy server in parallel processes, each its own run, and `dojo report` merges them into one leaderboard; a
job that fails in its launcher's process fails the sweep (exit 1), as it fails a sweep run in turn."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from dojo.evaluation.results_store import ResultsStore

pytest.importorskip("hydra_plugins.hydra_joblib_launcher", reason="needs the sweep extra: hydra-joblib-launcher")

PACK = Path(__file__).resolve().parents[1] / "specs" / "pack"
BASE = ["run", "-m", "hydra/launcher=joblib", f"packs=[{PACK}]", "suite=mini_test", "episodes=1", "num_envs=2",
        "progress=quiet", "policy=remote"]


def dojo(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, DOJO_PLAN_CACHE=str(cwd / "plans"), DOJO_OUTPUTS=str(cwd / "outputs"))
    return subprocess.run([sys.executable, "-m", "dojo.cli.main", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_sweep_over_two_policy_servers_runs_in_parallel_and_reports_one_leaderboard(tmp_path: Path) -> None:
    ports = {"zero": free_port(), "random": free_port()}
    servers = [subprocess.Popen([sys.executable, "-m", "xpolicylab.serve", f"policy={name}", f"port={port}"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for name, port in ports.items()]
    try:
        urls = ",".join(f"ws://127.0.0.1:{port}" for port in ports.values())
        done = dojo([*BASE, f"policy.url={urls}"], tmp_path)
    finally:
        for server in servers:
            server.terminate()
            server.wait(timeout=30)
    assert done.returncode == 0, done.stderr
    assert "launching 2 jobs" in done.stdout + done.stderr  # by joblib, in parallel processes
    runs: dict[str, int] = {}
    for path in (tmp_path / "outputs").rglob("results.sqlite"):
        with ResultsStore(path, readonly=True) as store:
            for row in store.rows():
                runs[row.policy_name] = runs.get(row.policy_name, 0) + 1
    assert runs == {"zero": 2, "random": 2}  # one run per server, every episode of each (the suite's two seeds)

    report = dojo(["report", str(tmp_path / "outputs" / "mini_test"), "--out", str(tmp_path / "report")], tmp_path)
    assert report.returncode == 0, report.stderr
    entries = json.loads((tmp_path / "report" / "report.json").read_text())["entries"]
    assert sorted(entry["policy"] for entry in entries) == ["random", "zero"]


def test_a_job_that_fails_in_a_launchers_process_fails_the_sweep(tmp_path: Path) -> None:
    closed = free_port()  # nothing listens there: the job cannot reach its policy
    done = dojo([*BASE, f"policy.url=ws://127.0.0.1:{closed}", "policy.protocol=xpolicylab,openpi"], tmp_path)
    assert done.returncode == 1
    assert f"could not connect to ws://127.0.0.1:{closed}" in done.stderr
