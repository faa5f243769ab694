"""`dojo run` end to end on the small test pack: results, report, a real kill -9 and resume, a served policy."""

from __future__ import annotations

import os
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dojo.evaluation.results_store import ResultsStore

PACK = Path(__file__).resolve().parents[1] / "specs" / "pack"
BASE = ["run", f"packs=[{PACK}]", "suite=mini_test", "episodes=3", "num_envs=2", "progress=quiet"]


def dojo(*args: str, cwd: Path, **kwargs) -> subprocess.Popen | subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "dojo.cli.main", *args]
    env = dict(os.environ, DOJO_PLAN_CACHE=str(cwd / "plan-cache"))
    if kwargs.pop("background", False):
        return subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=kwargs.pop("timeout", 600))


def episodes(path: Path) -> dict[tuple, tuple]:
    with ResultsStore(path, readonly=True) as store:
        return {row.key: (row.success, row.score, row.steps, row.failure_reason) for row in store.rows()}


def test_run_records_every_episode_and_writes_the_report(tmp_path: Path) -> None:
    result = dojo(*BASE, f"results={tmp_path / 'r.sqlite'}", f"report={tmp_path / 'report.json'}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    rows = episodes(tmp_path / "r.sqlite")
    assert len(rows) == 6  # 3 episodes x the suite's two seeds
    assert all(not success and reason == "horizon" for success, _, _, reason in rows.values())
    with ResultsStore(tmp_path / "r.sqlite", readonly=True) as store:
        assert {row.backend for row in store.rows()} == {"mujoco"}  # each row names the backend that ran it
    assert "overall" in result.stdout and "stack_test" in result.stdout
    assert (tmp_path / "report.json").is_file() and (tmp_path / "report.html").is_file()
    assert "mini_test: 6 plans (6 compiled in" in result.stderr  # the wait for compiling, said


def started(store: Path) -> subprocess.Popen:
    """`dojo run` of BASE in the background, returned once it has stored two episodes (and is still running)."""
    proc = dojo(*BASE, f"results={store}", cwd=store.parent, background=True)
    deadline = time.monotonic() + 300
    count = 0
    while time.monotonic() < deadline and proc.poll() is None:
        if store.exists():
            try:
                with sqlite3.connect(f"file:{store}?mode=ro", uri=True) as db:
                    count = db.execute("SELECT COUNT(*) FROM episodes").fetchone()[0]
            except sqlite3.OperationalError:
                count = 0
        if count >= 2:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it could be stopped"
    return proc


def test_sigterm_stops_the_run_as_ctrl_c_does_and_it_resumes(tmp_path: Path) -> None:
    """A scheduler's stop (SIGTERM): the run says why it stopped, exits 143, keeps what ended and resumes."""
    store = tmp_path / "stopped.sqlite"
    proc = started(store)
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 143, stderr.decode()
    assert "dojo run: stopped by SIGTERM" in stderr.decode() and "Traceback" not in stderr.decode()
    partial = episodes(store)
    assert 2 <= len(partial) < 6
    resumed = dojo(*BASE, f"results={store}", cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    after = episodes(store)
    assert len(after) == 6 and all(after[key] == value for key, value in partial.items())


def test_kill_9_and_resume_loses_and_repeats_nothing(tmp_path: Path) -> None:
    store = tmp_path / "killed.sqlite"
    proc = started(store)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    partial = episodes(store)
    assert 2 <= len(partial) < 6

    resumed = dojo(*BASE, f"results={store}", cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    assert "compiled in" not in resumed.stderr  # every plan reused: nothing to say
    after = episodes(store)
    assert len(after) == 6
    assert all(after[key] == value for key, value in partial.items())  # finished episodes were not re-run

    clean = dojo(*BASE, f"results={tmp_path / 'clean.sqlite'}", cwd=tmp_path)
    assert clean.returncode == 0, clean.stderr
    assert episodes(tmp_path / "clean.sqlite") == after  # the same results as an uninterrupted run


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("protocol", ["xpolicylab", "openpi"])
def test_run_against_a_served_policy(tmp_path: Path, protocol: str) -> None:
    port = _free_port()
    server = subprocess.Popen([sys.executable, "-m", "xpolicylab.serve", "policy=zero", f"protocol={protocol}",
                               f"port={port}"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        result = dojo(*BASE, "episodes=1", "policy=remote", f"policy.url=ws://127.0.0.1:{port}",
                      f"policy.protocol={protocol}", f"results={tmp_path / 'r.sqlite'}", cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        rows = episodes(tmp_path / "r.sqlite")
        assert len(rows) == 2
    finally:
        server.terminate()
        server.wait(timeout=30)


FAILING_POLICY = '''
import numpy as np
from xpolicylab.model import Model as Base, PolicyMetadata


class Model(Base):
    """Answers the first observation of every episode, then fails: a policy bug on some inputs."""

    @property
    def metadata(self):
        return PolicyMetadata(name="flaky", cameras=(), chunk_size=4, image_width=None, image_height=None)

    def reset(self):
        pass

    def update_obs(self, obs):
        self.pose = np.asarray(obs["state"]["joint_pos"], np.float32)
        self.step = int(obs["meta"]["step"])

    def get_action(self):
        if self.step > 0:
            raise RuntimeError("model crashed on this input")
        return np.repeat(self.pose[None], 4, axis=0)
'''


def test_a_policy_that_fails_ends_only_its_episodes(tmp_path: Path) -> None:
    (tmp_path / "flaky.py").write_text(FAILING_POLICY)
    port = _free_port()
    server = subprocess.Popen([sys.executable, "-m", "xpolicylab.serve", f"policy={tmp_path / 'flaky.py'}",
                               f"port={port}"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        result = dojo(*BASE, "episodes=1", "policy=remote", f"policy.url=ws://127.0.0.1:{port}",
                      f"results={tmp_path / 'r.sqlite'}", cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        rows = episodes(tmp_path / "r.sqlite")
        assert len(rows) == 2, rows
        assert all(not success and reason.startswith("policy_error") and steps == 4
                   for success, _, steps, reason in rows.values()), rows
    finally:
        server.terminate()
        server.wait(timeout=30)


CAMERA_POLICY = '''
import numpy as np
from xpolicylab.model import Model as Base, PolicyMetadata


class Model(Base):
    """Reads the head camera at 64x48 and holds the pose."""

    @property
    def metadata(self):
        return PolicyMetadata(name="looker", cameras=("head",), chunk_size=50, image_width=64, image_height=48)

    def update_obs(self, obs):
        assert obs["images"]["head"].shape == (48, 64, 3)
        self.pose = np.asarray(obs["state"]["joint_pos"], np.float32)

    def get_action(self):
        return np.repeat(self.pose[None], 50, axis=0)
'''


def test_a_run_says_what_it_renders_before_it_starts(tmp_path: Path) -> None:
    """Cameras are most of a CPU run's time: the run names them, their size, the most images and the time."""
    (tmp_path / "looker.py").write_text(CAMERA_POLICY)
    port = _free_port()
    server = subprocess.Popen([sys.executable, "-m", "xpolicylab.serve", f"policy={tmp_path / 'looker.py'}",
                               f"port={port}"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        args = (*BASE, "episodes=1", "policy=remote", f"policy.url=ws://127.0.0.1:{port}", "progress=jsonl",
                "tasks=[stack_test]")
        result = dojo(*args, cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        assert "policy looker reads 1 camera(s) (head) at 64x48: up to " in result.stderr
        assert "images for 2 episode(s), about " in result.stderr and "images/s measured" in result.stderr
        # The folder is named by what is evaluated, not by the server's address.
        stores = list((tmp_path / "outputs" / "mini_test" / "remote").glob("*/results.sqlite"))
        assert [s.parent.name for s in stores] == [f"episodes=1_packs={_safe(PACK)}_tasks=stack_test"]
    finally:
        server.terminate()
        server.wait(timeout=30)


def _safe(path: Path) -> str:
    from dojo.evaluation.run_dir import run_key

    return run_key([f"packs=[{path}]"]).split("=", 1)[1]


def test_tasks_keeps_only_those_of_the_suite(tmp_path: Path) -> None:
    result = dojo(*BASE, "tasks=[stack_tset]", cwd=tmp_path)
    assert result.returncode == 1
    assert "suite mini_test has no task 'stack_tset' (did you mean 'stack_test'?)" in result.stderr


@pytest.mark.slow
def test_dojo_run_with_no_arguments(tmp_path: Path) -> None:
    """The main job right after set-up: the default suite, the built-in reference policy, the CPU backend. CI runs
    the same command through the README's quick start (tests/test_readme.py), which does not shorten it; this
    test adds what the quick start does not check (slow: the whole suite twice in one CI run was 105 s)."""
    result = dojo("run", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "overall" in result.stdout and "stack_blocks" in result.stdout
    # The default policy is the privileged oracle: its table says so, plainly.
    assert "privileged reference: reads the simulator state, not a leaderboard entry" in result.stdout
    stores = list((tmp_path / "outputs").rglob("results.sqlite"))
    assert stores == [tmp_path / "outputs" / "robodojo_sim_mini" / "oracle" / "default" / "results.sqlite"]
    assert len(episodes(stores[0])) == 22  # 11 tasks x 2 episodes
    assert sorted(p.name for p in tmp_path.iterdir()) == ["outputs", "plan-cache"]  # nothing else in the cwd


RECORDING_PACK = Path(__file__).resolve().parents[1] / "recording" / "pack"


@pytest.mark.slow
def test_oracle_runs_on_mjx_and_agrees_with_mujoco(tmp_path: Path) -> None:
    """The same suite, seeds and scripted policy on both backends (minutes of XLA compilation on a CPU)."""
    from dojo.bench.backend_agreement import main as agreement

    common = ["run", f"packs=[{RECORDING_PACK}]", "suite=short_suite", "num_envs=1", "progress=quiet",
              "record=head", "width=160", "height=120"]
    for backend in ("mujoco", "mjx"):
        (tmp_path / backend).mkdir()
        result = dojo(*common, f"backend={backend}", f"results={tmp_path / backend}.sqlite", cwd=tmp_path / backend,
                      timeout=3600)
        assert result.returncode == 0, result.stderr
        assert len(episodes(tmp_path / f"{backend}.sqlite")) == 2  # num_envs=1: the slot was refilled once
        assert len(list((tmp_path / backend).rglob("*.mp4"))) == 2  # the head camera, rendered on both backends
    assert agreement([str(tmp_path / "mujoco.sqlite"), str(tmp_path / "mjx.sqlite")]) == 0
