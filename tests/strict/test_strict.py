"""`dojo validate --strict` as a contributor runs it: the example pack passes, each planted defect of the broken
pack is reported by its own check with a clear message, the JUnit file shows each check as a test case, a re-run
redoes only what changed, and `dojo new task` + `--strict` round-trips.

CI runs 2 seeds; the built-in tasks at 20 seeds (the issue's bar) are `-m slow`. No timing is asserted.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from xml.etree import ElementTree as ET

import pytest

from dojo.cli.new_cmd import new_main
from dojo.cli.validate_cmd import validate_main

REPO = Path(__file__).resolve().parents[2]
BROKEN = REPO / "tests" / "strict" / "broken_pack"
EXAMPLE = REPO / "examples" / "task_pack"
CHECKS = ["schema", "safety", "asset", "determinism", "stability", "solvability", "not_trivial", "horizon"]
PLANTED = {  # task -> (the check that must fail, words its message must say)
    "code_injection": ("safety", ["tag 'tag:yaml.org,2002:python/object/apply:os.system' is not allowed",
                                  "'_target_' is not allowed", "'${...}' interpolation is not allowed"]),
    "too_many_objects": ("safety", ["the scene holds up to 75 objects (75 placed, 0 clutter): at most 64"]),
    "giant_mesh": ("asset", ["asset 'giant_mug' measures 80 x 80 x 100 m (at scale 1): lengths are metres"]),
    "open_mesh": ("asset", ["collision mesh open_cup.obj is not watertight: 12 edges border a hole"]),
    "unstable": ("stability", ["none of 6 layouts of setting standard, seed 0 settled with the robot at home"]),
    "unsolvable": ("solvability", ["the scripted expert succeeds on 0 of 2 seeds, below 95%"]),
    "trivially_solved": ("not_trivial", ["the zero policy succeeds on 2 of 2 seeds",
                                         "the task is solved by doing nothing"]),
}


def dojo(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    result = subprocess.run([sys.executable, "-m", "dojo.cli.main", *args], capture_output=True, text=True,
                            cwd=cwd, timeout=900, env={**os.environ, "COLUMNS": "200"})
    assert "Traceback" not in result.stderr, result.stderr
    return result


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> tuple[subprocess.CompletedProcess, dict, ET.Element]:
    """Both packs at once, 2 seeds, as JSON and JUnit."""
    out = tmp_path_factory.mktemp("strict")
    result = dojo("validate", "--strict", str(EXAMPLE), str(BROKEN), "--seeds", "2", "-j", "2", "--format", "json",
                  "--junit", str(out / "report.xml"), "--cache", str(out / "cache"))
    return result, json.loads(result.stdout), ET.parse(out / "report.xml").getroot()


def _rows(data: dict) -> dict[str, dict]:
    return {row["task"] or f"pack {Path(row['pack']).name}": row for row in data["rows"]}


def test_each_planted_defect_is_caught_by_its_own_check(report) -> None:
    result, data, _ = report
    assert result.returncode == 1 and not data["valid"]
    rows = _rows(data)
    for task, (check, words) in PLANTED.items():
        statuses = {c["check"]: c["status"] for c in rows[task]["checks"]}
        assert [c["check"] for c in rows[task]["checks"]] == CHECKS
        first_failure = next(c for c in rows[task]["checks"] if c["status"] == "fail")
        assert first_failure["check"] == check, (task, statuses)
        after = CHECKS[CHECKS.index(check) + 1:]
        assert all(statuses[c] == "skip" for c in after), (task, statuses)
        before = CHECKS[:CHECKS.index(check)]
        assert all(statuses[c] in ("pass", "skip") for c in before), (task, statuses)
        messages = " | ".join(f["message"] for f in first_failure["findings"])
        for word in words:
            assert word in messages, (task, messages)
    # the injection was refused by the loader: judged by safety alone, never built
    assert _rows(data)["code_injection"]["checks"][0]["status"] == "skip"


def test_the_example_pack_passes_every_check(report) -> None:
    _, data, _ = report
    rows = _rows(data)
    example = rows["sort_fruit_onto_plates"]
    assert example["passed"], example
    assert [c["status"] for c in example["checks"]] == ["pass"] * len(CHECKS)
    assert rows["pack task_pack"]["passed"] and rows["pack broken_pack"]["passed"]
    horizon = example["checks"][-1]["figure"]
    assert horizon.startswith("expert p90 ") and "<= horizon 900" in horizon


def test_junit_has_one_case_per_task_and_check(report) -> None:
    _, data, junit = report
    cases = junit.findall(".//testcase")
    assert len(cases) == sum(len(row["checks"]) for row in data["rows"])
    failed = {(c.get("classname").rsplit(".", 1)[1], c.get("name")) for c in cases if c.find("failure") is not None}
    assert failed == {(task, check) for task, (check, _) in PLANTED.items()}
    assert int(junit.get("failures")) == len(PLANTED)
    unsolvable = next(c for c in cases if c.get("classname").endswith(".unsolvable") and c.get("name") == "solvability")
    assert "below 95%" in unsolvable.find("failure").get("message")


def test_a_rerun_redoes_only_the_task_that_changed(tmp_path: Path) -> None:
    pack, cache = tmp_path / "pack", tmp_path / "cache"
    (pack / "tasks").mkdir(parents=True)
    for name in ("trivially_solved", "unsolvable"):
        shutil.copy(BROKEN / "tasks" / f"{name}.yaml", pack / "tasks")
    args = ("validate", "--strict", str(pack), "--seeds", "2", "-j", "1", "--format", "json", "--cache", str(cache))
    first = dojo(*args)
    results = set((cache / "results").iterdir())
    assert first.returncode == 1 and len(results) == 4  # 2 tasks x 2 seeds, one record file per plan
    again = dojo(*args)
    assert _rows_without_seconds(again) == _rows_without_seconds(first)
    assert set((cache / "results").iterdir()) == results  # nothing redone

    task = pack / "tasks" / "trivially_solved.yaml"
    task.write_text(task.read_text().replace("success: {on: [block, table]}", "success: {lifted: [block, 0.05]}"))
    fixed = dojo(*args)
    new = set((cache / "results").iterdir()) - results
    kinds = [{key.split("@")[0] for key in json.loads(f.read_text())} for f in new]  # key@code fingerprint
    assert len(new) == 2 and all(k >= {"plan", "expert"} for k in kinds)
    rows, before = _rows_without_seconds(fixed), _rows_without_seconds(first)
    assert rows["trivially_solved"]["checks"][CHECKS.index("solvability")]["status"] == "fail"  # now it is not
    assert rows["unsolvable"] == before["unsolvable"]


def _rows_without_seconds(result: subprocess.CompletedProcess) -> dict[str, dict]:
    """The report's rows by task, less the seconds each check took (those differ between runs)."""
    return {name: {**row, "checks": [{k: v for k, v in c.items() if k != "seconds"} for c in row["checks"]]}
            for name, row in _rows(json.loads(result.stdout)).items()}


def test_new_task_then_strict_round_trip(tmp_path: Path) -> None:
    made = dojo("new", "task", "my_pack/my_task", cwd=tmp_path)
    assert made.returncode == 0, made.stderr
    assert (tmp_path / "my_pack" / "tasks" / "my_task.yaml").exists()
    assert (tmp_path / "my_pack" / "assets" / "my_task_block.yaml").exists()
    assert "dojo validate --strict my_pack/" in made.stdout
    assert dojo("validate", "my_pack/", cwd=tmp_path).returncode == 0
    strict = dojo("validate", "--strict", "my_pack/", "--seeds", "2", "-j", "2", "--cache", str(tmp_path / "cache"),
                  cwd=tmp_path)
    assert strict.returncode == 0, strict.stdout + strict.stderr
    assert "every check passed" in strict.stdout



def test_new_refuses_to_overwrite_or_shadow(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                            capsys: pytest.CaptureFixture) -> None:
    monkeypatch.chdir(tmp_path)
    assert new_main(["task", "my_pack/my_task"]) == 0
    assert new_main(["task", "my_pack/my_task"]) == 2 and "would overwrite" in capsys.readouterr().err
    assert new_main(["task", "my_pack/My-Task"]) == 2 and "is not a task id" in capsys.readouterr().err
    assert new_main(["task", "my_pack/stack_blocks"]) == 2 and "built-in id already" in capsys.readouterr().err
    assert new_main(["policy", "x"]) == 2 and "dojo policy new" in capsys.readouterr().err


def test_usage_errors_exit_2(tmp_path: Path) -> None:
    assert validate_main(["--strict", str(tmp_path / "missing")]) == 2
    assert validate_main(["--strict", str(EXAMPLE), "--seeds", "0"]) == 2
    assert validate_main(["--strict"]) == 2


@pytest.mark.slow
def test_every_builtin_task_passes_strict_at_20_seeds(tmp_path: Path) -> None:
    """The issue's bar: every built-in task passes `dojo validate --strict specs/ --seeds 20` (the wall time is
    printed, not asserted)."""
    result = dojo("validate", "--strict", "specs/", "--seeds", "20", "-j", str(max(2, os.cpu_count() or 1)),
                  "--cache", str(tmp_path / "cache"))
    print(result.stdout[-3000:])
    assert result.returncode == 0, result.stdout[-5000:]
