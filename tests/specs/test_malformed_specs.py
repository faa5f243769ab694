"""The malformed-spec corpus: every file gets exactly one problem, at the exact place, with the exact message.

Each file under `malformed/` starts with `# expect: LINE:COL $.json.path: message` (the message may be a prefix of
the full one). The file is validated inside a copy of the small valid pack in `pack/`, so that everything it
refers to exists and the one problem it carries is the only one.
"""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import pytest

from dojo.compiler.spec_library import SpecLibrary
from dojo.compiler.spec_yaml import MAX_SPEC_BYTES

HERE = Path(__file__).parent
CORPUS = sorted((HERE / "malformed").glob("*.yaml"))
EXPECT = re.compile(r"^# expect: (\d+):(\d+) (\$\S*): ?(.*)$")


@pytest.fixture
def pack(tmp_path: Path) -> Path:
    root = tmp_path / "pack"
    shutil.copytree(HERE / "pack", root)
    return root


def problems_for(pack: Path, name: str, text: str | bytes) -> list:
    target = pack / "extra" / name.split("__")[-1]
    target.parent.mkdir(exist_ok=True)
    target.write_bytes(text if isinstance(text, bytes) else text.encode())
    return pack_problems(pack)


def pack_problems(pack: Path) -> list:
    """Problems in the pack's own files (the built-in package is checked by its own tests)."""
    return [p for p in SpecLibrary.load([pack], strict=False).problems if Path(p.file).is_relative_to(pack)]


def test_corpus_is_large_enough() -> None:
    assert len(CORPUS) >= 30


@pytest.mark.parametrize("path", CORPUS, ids=[p.stem for p in CORPUS])
def test_malformed_spec(path: Path, pack: Path) -> None:
    text = path.read_text()
    match = EXPECT.match(text.splitlines()[0])
    assert match, f"{path.name} lacks its '# expect:' line"
    line, col, json_path, message = int(match[1]), int(match[2]), match[3], match[4]
    problems = problems_for(pack, path.name, text)
    assert len(problems) == 1, "\n".join(map(str, problems))
    problem = problems[0]
    assert problem.file.endswith(f"extra/{path.name.split('__')[-1]}")
    rendered = str(problem).split(": ", 1)[1]
    assert (problem.line, problem.column) == (line, col), str(problem)
    assert rendered.startswith(f"{json_path}: {message}"), str(problem)


def test_the_valid_pack_is_valid(pack: Path) -> None:
    assert pack_problems(pack) == []
    library = SpecLibrary.load([pack], strict=False)
    assert {s.id for s in library.specs if s.package != "builtin"} == {"test_block", "test_plate", "stack_test",
                                                                         "mini_test"}


def test_huge_file_is_rejected_before_parsing(pack: Path) -> None:
    text = "kind: task\nversion: 1\nid: huge\n# " + "x" * MAX_SPEC_BYTES + "\n"
    problems = problems_for(pack, "huge.yaml", text)
    assert len(problems) == 1
    assert (problems[0].line, problems[0].column) == (1, 1)
    assert "specs may be at most" in problems[0].message


def test_symlink_leaving_the_package_is_rejected(pack: Path, tmp_path: Path) -> None:
    outside = tmp_path / "outside.obj"
    outside.write_text("v 0 0 0\n")
    (pack / "extra").mkdir()
    os.symlink(outside, pack / "extra" / "escape.obj")
    text = ("kind: asset\nversion: 1\nid: escape\nclass: rigid\ncategory: x\nnames: [x]\n"
            "geoms:\n  - type: mesh\n    mesh: escape.obj\nmass: 0.1\n")
    problems = problems_for(pack, "escape.yaml", text)
    assert len(problems) == 1
    assert (problems[0].line, problems[0].column) == (9, 11)
    assert "resolves outside the spec's package" in problems[0].message


def test_non_utf8_file(pack: Path) -> None:
    problems = problems_for(pack, "latin1.yaml", b"kind: task\nversion: 1\nid: caf\xe9\n")
    assert len(problems) == 1
    assert (problems[0].line, problems[0].message) == (3, "file is not valid UTF-8")


def test_all_problems_of_a_file_are_reported_at_once(pack: Path) -> None:
    text = (HERE / "malformed" / "unknown_key_title.yaml").read_text().replace("version: 1", "version: 2")
    text = text.replace("horizon: 300", "horizon: -5")
    problems = problems_for(pack, "unknown_key_title.yaml", text)
    assert [p.path for p in problems] == [("version",), ("titel",), ("horizon",)]
