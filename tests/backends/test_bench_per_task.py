"""`dojo bench sim backend=mujoco` over several tasks also measures each task's scenes alone, in the same run
(how much a heavy scene, many small bodies, slows the CPU backend against a light one). Never a time."""

from __future__ import annotations

import json
import subprocess
import sys


def test_several_tasks_get_per_task_rates(tmp_path):
    result = subprocess.run([sys.executable, "-m", "dojo.cli.main", "bench", "sim", "backend=mujoco",
                             "tasks=[stack_blocks,play_xylophone]", "episodes=1", "num_envs=2", "steps=3"],
                            cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    out = json.loads(result.stdout.strip().splitlines()[-1])
    assert set(out["per_task"]) == {"stack_blocks", "play_xylophone"} == set(out["tasks"])
    for rates in out["per_task"].values():
        assert rates["interactions_per_cpu_s"] > 0
        assert rates["physics_steps_per_cpu_s"] == 20 * rates["interactions_per_cpu_s"]  # 500 Hz under 25 Hz
