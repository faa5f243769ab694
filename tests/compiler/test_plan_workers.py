"""Plans compiled in worker processes: the same files as in-process, and never a fork of a threaded process.

`dojo run -j 2` (and `dojo compile`, `dojo collect`, the validity table) may run after JAX started its threads in
the same process; a forked copy of a multithreaded process can deadlock, and JAX warns about it. Workers are
spawned instead, and recording a video starts ffmpeg without Python code between fork and exec.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

PACK = Path(__file__).resolve().parents[1] / "specs" / "pack"

SCRIPT = textwrap.dedent("""
    import sys, warnings
    from pathlib import Path
    import jax, numpy as np
    jax.devices()  # JAX's runtime threads are up: forking from here on is what JAX warns about
    from dojo.compiler.spec_library import SpecLibrary
    from dojo.compiler.suite_compile import compile_suite
    from dojo.evaluation.recorder import Mp4Writer

    library = SpecLibrary.load([Path(sys.argv[1])])
    suite = library.get("suite", "mini_test")
    for jobs in (2, 1):
        stats = compile_suite(library, suite, Path(sys.argv[2]) / f"jobs{jobs}", jobs=jobs, seeds=[0], episodes=2,
                              tasks=["stack_test"])
        print(jobs, stats.compiled)
    writer = Mp4Writer(Path(sys.argv[2]) / "v.mp4", fps=10)
    for _ in range(2):
        writer.write(np.zeros((48, 64, 3), np.uint8))
    writer.close()
""")


def test_compiling_in_workers_after_jax_started_never_forks(tmp_path: Path) -> None:
    result = subprocess.run([sys.executable, "-W", "always", "-c", SCRIPT, str(PACK), str(tmp_path)],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["2", "2", "1", "2"]  # both ways compiled the 2 plans of seed 0
    assert "os.fork()" not in result.stderr, result.stderr
    spawned = sorted(p.relative_to(tmp_path / "jobs2") for p in (tmp_path / "jobs2").rglob("*.json"))
    inline = sorted(p.relative_to(tmp_path / "jobs1") for p in (tmp_path / "jobs1").rglob("*.json"))
    assert spawned == inline
    for path in spawned:
        if path.name != "index.json":
            assert (tmp_path / "jobs2" / path).read_bytes() == (tmp_path / "jobs1" / path).read_bytes()
    assert (tmp_path / "v.mp4").stat().st_size > 0


def test_auto_starts_a_worker_per_cpu_only_when_each_has_plans_enough_to_repay_its_start(monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    from dojo.compiler.suite_compile import PLANS_PER_WORKER, worker_count

    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(16)))
    assert worker_count("auto", 1) == 1
    assert worker_count("auto", 2 * PLANS_PER_WORKER - 1) == 1
    assert worker_count("auto", 3 * PLANS_PER_WORKER) == 3
    assert worker_count("auto", 6_144) == 16  # no more than the CPUs this process may use
    assert worker_count(4, 1) == worker_count("4", 1) == 4  # a number is taken as given (Hydra may pass a string)
    for bad in (0, "many", None):
        with pytest.raises(ValueError, match="jobs="):
            worker_count(bad, 10)
