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


def _bench_error(cwd, folder: str, tasks: str) -> str:
    result = subprocess.run([sys.executable, "-m", "dojo.cli.main", "bench", "sim", "backend=mujoco",
                             f"plans={folder}", f"tasks={tasks}", "num_envs=2", "steps=1"],
                            cwd=cwd, capture_output=True, text=True, timeout=300)
    assert result.returncode != 0
    return result.stderr


def test_a_plans_folder_that_holds_no_plan_of_the_tasks_is_named_in_the_error(tmp_path):
    """A bench over an empty or missing folder, or with a task filter matching none of its plans, fails at once
    with the folder in the message, not later with an index error far from the cause."""
    from dojo.compiler.plan import compile_plan
    from dojo.compiler.spec_library import SpecLibrary

    (tmp_path / "plans").mkdir()
    for folder in ("plans", "missing"):
        stderr = _bench_error(tmp_path, folder, "[stack_blocks]")
        assert f"plans={folder}: no plan files (*.json) in {tmp_path / folder}" in stderr, stderr
    library = SpecLibrary.load([])
    compile_plan(library, library.get("task", "push_t"), "standard", 0).save(tmp_path / "plans" / "push_t.json")
    stderr = _bench_error(tmp_path, "plans", "[stack_blocks]")
    assert f"plans=plans: no plan of ['stack_blocks'] in {tmp_path / 'plans'}" in stderr, stderr


def test_a_compiled_suite_folder_is_benched_on_the_plans_its_index_lists(tmp_path):
    """`plans=` pointed at `dojo compile`'s output reads its index (plans live in one folder per task): every
    distinct plan of the suite's episodes, in the protocol's order, random setting included; `episodes` keeps at
    most that many a task."""
    from dojo.bench.sim_bench import load_plans
    from dojo.compiler.spec_library import SpecLibrary
    from dojo.compiler.suite_compile import compile_suite

    library = SpecLibrary.load([])
    stats = compile_suite(library, library.get("suite", "robodojo_sim_mini"), tmp_path, seeds=[0, 1], episodes=4,
                          tasks=["stack_blocks", "push_t"])
    index = json.loads((tmp_path / "index.json").read_text())["plans"]
    distinct = list(dict.fromkeys(entry["hash"] for entry in index))
    assert len(index) == stats.plans
    assert [p.hash for p in load_plans({"plans": str(tmp_path), "episodes": None})] == distinct
    assert {p.setting for p in load_plans({"plans": str(tmp_path), "episodes": None})} == {"standard", "random"}
    kept = load_plans({"plans": str(tmp_path), "episodes": 1, "tasks": ["push_t"]})
    assert [p.hash for p in kept] == [next(e["hash"] for e in index if e["task"] == "push_t")]
    # `dojo bench render` reads the same folder through the same index
    from dojo.bench.render_bench import bench_plans

    assert [p.hash for p in bench_plans({"plans": str(tmp_path)})] == distinct
