"""The README is tested: its quick start runs as a new user runs it, and every `dojo` command in it parses.

The quick start (the `bash` blocks under `## Quick start`) is run in order by one bash process, in a fresh copy of
the repository, each command checked for exit code 0 and for the files its `# -> PATH, PATH` comment names.

- slow (`python -m pytest -m slow tests/test_readme.py`): exactly as written, set-up included (a new venv,
  `./setup.sh`), with an empty plan cache: what a new user lives through;
- fast (CI): the set-up line is left out (CI has just run `./setup.sh` in this interpreter's venv), and every
  `dojo run|compile|bench` gets `tasks=[stack_blocks] episodes=1` (where it does not set them), so a run
  folder's key in a `-> PATH` becomes `*`; except a bare `dojo run`, the first job after set-up, which runs as
  written (the whole default suite, then its resume).

Both replace the README's ports 19000 and 19001 by free ones, so that a server already listening there cannot
fail the test. Any other `dojo` command in the README (GPU, long jobs) is parsed: a known command whose Hydra
overrides compose, so that a renamed key or option fails the build too.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import socket
import subprocess
import sqlite3
import sys
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
DEFAULT_SUITE_TASKS = yaml.safe_load((REPO / "specs" / "suites" / "robodojo_sim_mini.yaml").read_text())["tasks"]
QUICK_OVERRIDES = {"tasks": "[stack_blocks]", "episodes": "1"}
SHORTENED = ("run", "compile", "bench")
README_PORTS = ("19000", "19001")


@dataclass(frozen=True)
class Command:
    """One line of a quick-start block: the command as typed, and the paths its `# -> ...` comment names."""

    text: str
    outputs: tuple[str, ...]
    line: int


def _blocks(text: str, section: str | None) -> list[tuple[int, list[str]]]:
    """(first line number, lines) of each ```bash block, only under the `## <section>` heading when given."""
    blocks, inside, current, start, in_section = [], False, [], 0, section is None
    for number, line in enumerate(text.splitlines(), 1):
        if line.startswith("## ") and section is not None:
            in_section = line[3:].strip() == section
        if line.startswith("```"):
            if inside:
                if in_section:
                    blocks.append((start, current))
                inside, current = False, []
            elif line.strip() == "```bash":
                inside, start = True, number + 1
            continue
        if inside:
            current.append(line)
    return blocks


def _split_comment(line: str) -> tuple[str, str]:
    """`command  # comment` -> (command, comment); a `#` inside quotes is part of the command."""
    for match in re.finditer(r"\s#\s", line):
        head = line[:match.start()]
        if head.count("'") % 2 == 0 and head.count('"') % 2 == 0:
            return head.strip(), line[match.end():].strip()
    return line.strip(), ""


def quick_start(text: str) -> list[Command]:
    """The quick start's commands in order."""
    commands = []
    for start, lines in _blocks(text, "Quick start"):
        for offset, raw in enumerate(lines):
            command, comment = _split_comment(raw)
            if not command:
                continue
            outputs = ()
            if "->" in comment:
                tail = comment.split("->", 1)[1]
                outputs = tuple(t.strip(",;()") for t in tail.replace(",", " ").split() if "/" in t)
            commands.append(Command(command, outputs, start + offset))
    return commands


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _shortened(command: Command) -> Command:
    """The fast variant of a command: `dojo run|compile|bench` on one task, one episode."""
    words = command.text.split()
    if len(words) < 3 or words[0] != "dojo" or words[1] not in SHORTENED:
        return command
    given = {w.split("=", 1)[0] for w in words if "=" in w}
    extra = " ".join(f"{k}={v}" for k, v in QUICK_OVERRIDES.items() if k not in given)
    outputs = command.outputs
    if words[1] == "run":  # outputs/<suite>/<policy>/<key>/...: the key now names the extra overrides too
        outputs = tuple("/".join(p if i != 3 else "*" for i, p in enumerate(o.split("/")))
                        if o.startswith("outputs/") and o.count("/") >= 4 else o for o in outputs)
    return Command(f"{command.text} {extra}".strip(), outputs, command.line)


def script(commands: list[Command], markers: Path) -> str:
    """One bash script: each command, then its start and end time and exit code, and any missing output, written
    to fd 3 (`markers`)."""
    out = [f"exec 3>{shlex.quote(str(markers))}",
           "trap 'kill $(jobs -p) 2>/dev/null; wait 2>/dev/null' EXIT"]
    for i, command in enumerate(commands):
        out.append(f"echo '>>> README line {command.line}: '{shlex.quote(command.text)}; t0=$EPOCHREALTIME")
        out.append(command.text)
        out.append(f"rc=$?; echo \"{i} $t0 $EPOCHREALTIME rc=$rc\" >&3; [ $rc -eq 0 ] || exit 1")
        for path in command.outputs:
            out.append(f"compgen -G {shlex.quote(path)} >/dev/null || {{ echo \"{i} missing {path}\" >&3; exit 1; }}")
    return "\n".join(out) + "\n"


def _git_files(*flags: str) -> list[str]:
    out = subprocess.run(["git", "ls-files", "-z", *flags], cwd=REPO, capture_output=True, text=True, check=True)
    return [name for name in out.stdout.split("\0") if name]


def _fresh_clone(dest: Path, made_by_readme: set[str]) -> Path:
    """The working tree's files that git would commit (tracked, or new and not ignored), as a new user's clone
    has them; untracked folders the quick start itself makes (`my_policy/` of a run in this checkout) are left
    out, or the copy would not be fresh."""
    names = _git_files("--cached") + [n for n in _git_files("--others", "--exclude-standard")
                                      if n.split("/")[0] not in made_by_readme]
    for name in names:
        source = REPO / name
        if source.is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, dest / name)
    return dest


def _run(commands: list[Command], tmp_path: Path, env: dict[str, str], timeout: int) -> None:
    ports = {p: str(_free_port()) for p in README_PORTS}
    commands = [Command(re.sub("|".join(ports), lambda m: ports[m.group(0)], c.text), c.outputs, c.line)
                for c in commands]
    clone = _fresh_clone(tmp_path / "robodojo", {o.split("/")[0] for c in commands for o in c.outputs})
    markers = tmp_path / "markers"
    result = subprocess.run(["bash", "-c", script(commands, markers)], cwd=clone, env=env, capture_output=True,
                            text=True, timeout=timeout)
    output = result.stdout + result.stderr
    log = output[-6000:]
    done = markers.read_text().splitlines() if markers.exists() else []
    failed = [m for m in done if not m.endswith(" rc=0")]
    if failed or len(done) != len(commands):
        where = commands[int((failed or done or ["0"])[-1].split()[0]) + (0 if failed or not done else 1)]
        pytest.fail(f"README line {where.line} failed ({failed[-1].split()[-1] if failed else 'no exit code'}): "
                    f"{where.text}\n{log}")
    # No red pip resolver report (or any tool's ERROR line), and no fork of a threaded process.
    assert not re.search(r"^ERROR\b", output, re.MULTILINE), output
    assert "os.fork()" not in output, output
    for marker, command in zip(done, commands):  # seconds per command, for the README's figures (pytest -s)
        _, start, end, _ = marker.split()
        print(f"{float(end) - float(start):8.1f} s  {command.text}")


def _env(tmp_path: Path, this_venv: bool) -> dict[str, str]:
    """The environment of the commands: an empty plan cache, and this interpreter's venv on the PATH (fast) or
    no venv at all (slow: the README creates and activates its own)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("DOJO_", "PYTEST", "VIRTUAL_ENV"))}
    env["DOJO_PLAN_CACHE"] = str(tmp_path / "plan-cache")
    bin_dir = str(Path(sys.executable).parent)
    path = [p for p in env.get("PATH", "").split(os.pathsep) if p and p != bin_dir]
    env["PATH"] = os.pathsep.join(([bin_dir] if this_venv else []) + path)
    return env


def test_readme_names_outputs_and_the_fast_variant_shortens_every_run() -> None:
    """The parser sees the quick start: the steps the issue named are there, with their outputs."""
    commands = quick_start(README.read_text())
    texts = [c.text for c in commands]
    assert texts[0].endswith("./setup.sh")
    assert "dojo run -m policy=zero,random" in texts
    report = texts.index("dojo report outputs/robodojo_sim_mini/zero outputs/robodojo_sim_mini/random")
    assert texts.index("dojo run -m policy=zero,random") < report
    assert any(t.startswith("dojo run policy=remote") for t in texts)
    assert any(t.startswith("dojo bench sim") for t in texts)
    assert all(c.outputs for c in commands if c.text.startswith(("dojo show", "dojo compile", "dojo report")))
    first_run = next(c for c in commands if c.text == "dojo run")
    assert first_run.outputs == ("outputs/robodojo_sim_mini/oracle/default/results.sqlite",)
    assert _shortened(first_run) == first_run  # run as written, in CI too
    sweep = _shortened(next(c for c in commands if c.text == "dojo run -m policy=zero,random"))
    assert sweep.text == "dojo run -m policy=zero,random tasks=[stack_blocks] episodes=1"
    assert sweep.outputs[0] == "outputs/robodojo_sim_mini/zero/*/results.sqlite"


def test_readme_quick_start_runs_in_order_on_one_task(tmp_path: Path) -> None:
    """Every quick-start command, shortened but for the plain `dojo run`: its reference policy solves every
    episode of the default suite, which is also CI's check that each of that suite's tasks' experts solves its
    two episodes (`tests/experts/test_validity.py` checks the other tasks' first seeds)."""
    commands = [_shortened(c) for c in quick_start(README.read_text()) if "./setup.sh" not in c.text]
    _run(commands, tmp_path, _env(tmp_path, this_venv=True), timeout=1500)
    store = tmp_path / "robodojo" / "outputs" / "robodojo_sim_mini" / "oracle" / "default" / "results.sqlite"
    with closing(sqlite3.connect(store)) as db:
        rows = db.execute("SELECT task, success, failure_reason FROM episodes").fetchall()
    assert len(rows) == 2 * len(DEFAULT_SUITE_TASKS) and {t for t, _, _ in rows} == set(DEFAULT_SUITE_TASKS)
    assert [r for r in rows if not r[1]] == []


@pytest.mark.slow
def test_readme_quick_start_runs_as_written_from_a_fresh_clone(tmp_path: Path) -> None:
    """A new user's first hour: a new venv, `./setup.sh`, then every quick-start command as written."""
    _run(quick_start(README.read_text()), tmp_path, _env(tmp_path, this_venv=False), timeout=3600)


def test_every_dojo_command_in_the_readme_parses() -> None:
    """Commands outside the quick start (GPU, long jobs) are not run here; their overrides must still compose."""
    from dojo.bench.ray_bench import split_arguments
    from dojo.bench.served_bench import OWN_KEYS as SERVED_KEYS
    from dojo.cli.main import COMMANDS, _jobs_flag, _what_word
    from dojo.cli.hydra_app import _register_spec_groups, check_overrides, overrides_of

    hydra_commands = {"run", "compile", "show", "bench", "collect"}
    checked = 0
    for _, lines in _blocks(README.read_text(), None):
        for raw in lines:
            command, _ = _split_comment(raw)
            words = shlex.split(command.rstrip("&").strip()) if command.startswith("dojo ") else []
            if len(words) < 2 or words[1].startswith("-") or words[1:3] == ["bench", "policy"]:
                continue
            if words[1:3] == ["bench", "ray"]:  # its own keys, then the overrides of the `dojo run` it times
                words = ["dojo", "run", *split_arguments(words[3:])[1]]
            elif words[1:3] == ["bench", "served"]:
                words = ["dojo", "run", *split_arguments(words[3:], SERVED_KEYS)[1]]
            assert words[1] in COMMANDS, command
            if words[1] not in hydra_commands:
                continue
            overrides = overrides_of(_jobs_flag(_what_word(words[2:]) if words[1] == "bench" else words[2:]))
            _register_spec_groups([])
            assert check_overrides(words[1], overrides) is None, command
            checked += 1
    assert checked >= 10
