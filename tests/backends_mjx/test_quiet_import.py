"""Importing the mjx backend prints nothing: `dojo bench` output is exactly one JSON line, warp or not."""

from __future__ import annotations

import subprocess
import sys


def test_importing_the_mjx_backend_keeps_stdout_clean():
    result = subprocess.run([sys.executable, "-c", "import dojo.backends.mjx.batch, dojo.bench.sim_bench"],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert result.stdout == ""
