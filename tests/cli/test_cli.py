"""The `dojo` command line as a user meets it: help, exit codes, Hydra overrides, and no tracebacks."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from dojo.cli.doctor import render_text
from dojo.cli.main import COMMANDS

REPO = Path(__file__).resolve().parents[2]
PACK = REPO / "tests" / "specs" / "pack"


def dojo(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    result = subprocess.run([sys.executable, "-m", "dojo.cli.main", *args], capture_output=True, text=True,
                            cwd=cwd, timeout=120)
    assert "Traceback" not in result.stderr, result.stderr
    return result


def test_top_level_help_lists_every_command() -> None:
    result = dojo("--help")
    assert result.returncode == 0
    for name in ("validate", "compile", "run", "bench", "list", "show", "report", "policy"):
        assert f"  {name} " in result.stdout


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_command_has_help_with_an_example(name: str) -> None:
    result = dojo(name, "--help")
    assert result.returncode == 0, result.stderr
    assert "example" in result.stdout.lower()
    assert "dojo " + name in result.stdout


def test_unknown_command_suggests_the_closest() -> None:
    result = dojo("valdate", "specs")
    assert result.returncode == 2
    assert "unknown command 'valdate' (did you mean 'validate'?)" in result.stderr


def test_validate_exit_codes_and_json(tmp_path: Path) -> None:
    ok = dojo("validate", str(PACK), "--format", "json")
    assert ok.returncode == 0, ok.stdout + ok.stderr
    report = json.loads(ok.stdout)
    assert report["valid"] and report["checked"] == {"asset": 2, "suite": 1, "task": 1}

    bad = tmp_path / "bad.yaml"
    bad.write_text("kind: suite\nversion: 1\nid: bad\ntasks: [no_such_task]\n")
    invalid = dojo("validate", str(bad))
    assert invalid.returncode == 1
    assert "bad.yaml:4:9: $.tasks[0]: unknown task 'no_such_task'" in invalid.stdout
    assert "1 problem(s) in 1 file(s)" in invalid.stderr

    assert dojo("validate", str(tmp_path / "missing")).returncode == 2
    assert dojo("validate", "--format", "xml", str(PACK)).returncode == 2


def test_validate_builtin_specs_from_the_repository() -> None:
    result = dojo("validate", "specs", "assets", cwd=REPO)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "all valid" in result.stdout


def test_list_shows_tasks_with_dimension_and_embodiment() -> None:
    result = dojo("list", "tasks", "--pack", str(PACK))
    assert result.returncode == 0, result.stderr
    assert "stack_test" in result.stdout and "generalization" in result.stdout and "arx_x5_bimanual" in result.stdout
    as_json = json.loads(dojo("list", "robots", "--format", "json").stdout)
    assert {"arx_x5_bimanual", "piper_bimanual", "piperx_bimanual"} <= {r["id"] for r in as_json}
    assert dojo("list", "taks").returncode == 2


def test_hydra_prints_the_composed_config() -> None:
    result = dojo("show", "robot=piper_bimanual", "seed=7", "--cfg", "job")
    assert result.returncode == 0, result.stderr
    assert "id: piper_bimanual" in result.stdout and "seed: 7" in result.stdout


def test_unknown_key_and_misspelled_option_name_the_closest() -> None:
    key = dojo("show", "sed=3")
    assert key.returncode == 2
    assert "unknown key 'sed' (did you mean 'seed'?)" in key.stderr
    option = dojo("bench", "backend=mjz")
    assert option.returncode == 2
    assert "unknown backend 'mjz' (did you mean 'mjx'?)" in option.stderr
    robot = dojo("show", "robot=piper_bimanul")
    assert "unknown robot 'piper_bimanul' (did you mean 'piper_bimanual'?)" in robot.stderr


def test_multirun_sweeps_with_the_basic_launcher(tmp_path: Path) -> None:
    result = dojo("show", "-m", "seed=1,2", cwd=tmp_path)
    assert result.stdout.count("#0 : seed=1") + result.stderr.count("#0 : seed=1") == 1
    assert "#1 : seed=2" in result.stdout + result.stderr


def test_show_renders_a_robot_and_a_task_to_png(tmp_path: Path) -> None:
    from PIL import Image
    import numpy as np

    default = dojo("show", "robot=piper_bimanual", "width=32", "height=24", cwd=tmp_path)
    assert default.returncode == 0, default.stderr
    assert (tmp_path / "outputs" / "show" / "piper_bimanual_head.png").is_file()  # under the results root
    robot = dojo("show", "robot=piper_bimanual", f"out={tmp_path}", "width=160", "height=120")
    assert robot.returncode == 0, robot.stderr
    task = dojo("show", "task=stack_blocks", "setting=random", "seed=2", f"out={tmp_path}", "width=160",
                "height=120", "usd=true")
    assert task.returncode == 0, task.stderr
    assert "instruction: " in task.stdout
    for name in ("piper_bimanual_head", "stack_blocks-random-2_head", "stack_blocks-random-2_left_wrist",
                 "stack_blocks-random-2_overview"):
        image = np.asarray(Image.open(tmp_path / f"{name}.png"))
        assert image.shape == (120, 160, 3) and image.std() > 5, name
    assert (tmp_path / "stack_blocks-random-2.usda").read_text().startswith("#usda")


def test_compile_writes_plans_and_reuses_them(tmp_path: Path) -> None:
    args = ("compile", f"packs=[{PACK}]", "suite=mini_test", f"out={tmp_path / 'plans'}", "episodes=2", "-j", "2")
    first = dojo(*args)
    assert first.returncode == 0, first.stderr
    assert "4 plans (4 compiled" in first.stdout  # two episodes x the suite's two seeds
    second = dojo(*args)
    assert "(0 compiled" in second.stdout and "4 reused" in second.stdout
    assert (tmp_path / "plans" / "index.json").is_file()


def test_validate_with_no_path_checks_the_builtin_specs(tmp_path: Path) -> None:
    result = dojo("validate", cwd=tmp_path)  # anywhere: the installed package's own specs and assets
    assert result.returncode == 0, result.stdout + result.stderr
    assert "all valid" in result.stdout and " suite, " in result.stdout and " task, " in result.stdout
    assert " taxonomy)" in result.stdout


def test_a_broken_task_file_is_the_error_not_the_suite_that_uses_it(tmp_path: Path) -> None:
    pack = tmp_path / "pack"
    shutil.copytree(PACK, pack)
    task = pack / "tasks" / "stack_test.yaml"
    task.write_text(task.read_text().replace("dimension:", "dimensoin:", 1))
    result = dojo("validate", str(pack))
    assert result.returncode == 1
    lines = result.stdout.splitlines()
    assert "stack_test.yaml" in lines[0] and "unknown key 'dimensoin' (did you mean 'dimension'?)" in lines[0]
    assert all("unknown task" not in line for line in lines)
    assert "mini_test.yaml" in lines[1] and f"task 'stack_test' did not load: {task} is invalid" in lines[1]


def test_a_misspelt_key_names_the_key_and_does_not_suggest_adding_it() -> None:
    result = dojo("run", "polcy=zero")
    assert result.returncode == 2
    assert result.stderr.strip() == "dojo run: unknown key 'polcy' (did you mean 'policy'?)"
    new = dojo("run", "zzzz=1")
    assert "to add a new key write +zzzz=VALUE" in new.stderr


def test_a_bad_backend_setting_stops_the_run_before_it_starts(tmp_path: Path) -> None:
    """`registry.check_settings`: refused with the setting's name before anything runs, so no results store is
    made and no progress is printed."""
    results = tmp_path / "r.sqlite"
    result = dojo("run", "backend=mjx", "backend.merge=maybe", "policy=zero", "suite=robodojo_sim_mini",
                  "tasks=[push_t]", "episodes=1", "num_envs=1", f"results={results}", "progress=jsonl", cwd=tmp_path)
    assert result.returncode == 1 and not results.exists() and result.stdout == ""
    assert "dojo run: error: ValueError: backend.merge takes true, false or auto, not 'maybe'" in result.stderr


def test_an_unknown_routes_setting_stops_the_run_before_it_starts(tmp_path: Path) -> None:
    results = tmp_path / "r.sqlite"
    result = dojo("run", "routes=both", "policy=zero", "suite=robodojo_sim_mini", "tasks=[push_t]", "episodes=1",
                  "num_envs=1", f"results={results}", "progress=jsonl", cwd=tmp_path)
    assert result.returncode == 1 and not results.exists() and result.stdout == ""
    assert "dojo run: error: ValueError: routes must be one of side_by_side, in_turn, got 'both'" in result.stderr


def test_doctor_reports_versions_devices_and_folders(tmp_path: Path) -> None:
    result = subprocess.run([sys.executable, "-m", "dojo.cli.main", "doctor", "--format", "json"], cwd=tmp_path,
                            capture_output=True, text=True, timeout=120,
                            env={**os.environ, "DOJO_OUTPUTS": str(tmp_path / "results"),
                                 "DOJO_BUCKET_CACHE": str(tmp_path / "buckets")})
    assert result.returncode == 0, result.stderr
    facts = json.loads(result.stdout)
    assert facts["versions"]["robodojo"] and facts["versions"]["mujoco"] and facts["versions"]["jax"]
    assert facts["system"]["cpu_cores"] >= 1
    assert facts["devices"]["jax_backend"].split()[0] in ("cpu", "gpu", "cuda")
    assert set(facts["devices"]) == {"gpus", "jax_backend", "mujoco_warp", "rendering"}
    assert facts["folders"]["results_root"] == {"path": str(tmp_path / "results"), "exists": False, "bytes": 0,
                                                "runs": 0}
    assert facts["folders"]["bucket_cache"] == {"path": str(tmp_path / "buckets"), "exists": False, "bytes": 0}
    # The text form renders these same facts (the README's quick start runs `dojo doctor` itself).
    text = render_text(facts)
    assert "results_root" in text and "plan_cache" in text and f"{tmp_path / 'results'} (not created yet)" in text


def test_a_sweep_writes_where_single_runs_do_and_its_report_follows(tmp_path: Path) -> None:
    """`dojo run -m policy=zero,random` then `dojo report outputs/<suite>/zero outputs/<suite>/random`."""
    env_args = (f"packs=[{PACK}]", "suite=mini_test", "episodes=1", "progress=quiet")
    sweep = dojo("run", "-m", "policy=zero,random", *env_args, cwd=tmp_path)
    assert sweep.returncode == 0, sweep.stderr
    single = dojo("run", "policy=zero", *env_args, cwd=tmp_path)  # the sweep's job: resumed, nothing re-run
    assert single.returncode == 0, single.stderr
    stores = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("results.sqlite"))
    assert [p.parts[:3] for p in stores] == [("outputs", "mini_test", "random"), ("outputs", "mini_test", "zero")]
    report = dojo("report", "outputs/mini_test/zero", "outputs/mini_test/random", cwd=tmp_path)
    assert report.returncode == 0, report.stderr
    assert (tmp_path / "outputs" / "report" / "report.html").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["outputs"]  # no log or report in the working folder
