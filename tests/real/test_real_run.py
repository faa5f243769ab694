"""`dojo run backend=real` end to end against the emulator: a real suite (tests/real/pack: two short PiPER tasks,
two trials each) evaluated with a zero policy served over XPolicyLab, as a lab would run RealEval.

Checked: the run needs no num_envs (one robot is one slot whatever the run asks), every trial is a row of the
SQLite results store like a simulation episode, with its safety counters (every kind the safety layer counts)
and its video, an MP4 tiling every camera of the robot; the raters' job (success, score) is left undone.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import imageio.v3 as iio
import pytest

pytest.importorskip("can")
pytest.importorskip("piper_sdk")

from dojo.backends.real.safety import COUNTERS  # noqa: E402
from dojo.evaluation.results_store import ResultsStore  # noqa: E402

PACK = Path(__file__).parent / "pack"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_served_policy_runs_a_real_suite_on_the_emulator(tmp_path: Path, figures) -> None:
    port = _free_port()
    server = subprocess.Popen([sys.executable, "-m", "xpolicylab.serve", "policy=zero", f"port={port}"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    env = dict(os.environ, DOJO_PLAN_CACHE=str(tmp_path / "plan-cache"), DOJO_OUTPUTS=str(tmp_path / "outputs"))
    try:
        started = time.monotonic()
        result = subprocess.run(
            [sys.executable, "-m", "dojo.cli.main", "run", f"packs=[{PACK}]", "suite=real_probe", "backend=real",
             "policy=remote", f"policy.url=ws://127.0.0.1:{port}", "record=all", "width=64", "height=48",
             "progress=quiet", f"results={tmp_path / 'r.sqlite'}"],
            cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
        figures.add("dojo_run_backend_real.wall_s(2 tasks x 2 trials, horizons 30+20 steps, record=all 64x48)",
                    round(time.monotonic() - started, 1))
    finally:
        server.terminate()
        server.wait(timeout=30)
    assert result.returncode == 0, result.stderr
    with ResultsStore(tmp_path / "r.sqlite", readonly=True) as store:
        rows = store.rows()
    assert sorted((r.task, r.episode) for r in rows) == [
        ("piper_block_probe", 0), ("piper_block_probe", 0), ("piper_bowl_probe", 0), ("piper_bowl_probe", 1)]
    for row in rows:
        assert row.steps == {"piper_block_probe": 30, "piper_bowl_probe": 20}[row.task]
        assert row.failure_reason == "horizon" and not row.success and row.score == 0.0
        assert set(row.counters) == set(COUNTERS)
        assert all(row.counters[name] == 0 for name in COUNTERS if name.startswith("refused"))
        video = tmp_path / row.video_path
        frames = iio.imread(video)
        assert video.suffix == ".mp4" and len(frames) == row.steps + 1  # every observation, the last one too
        assert frames.shape[2] == 3 * 64  # head, left and right wrist cameras side by side
