"""Rules of the code base that a reviewer should not have to check by hand: the code is one `dojo/` tree whose
import paths are its file paths, no import cycle at module level, no engine built by hand outside its own backend
package, and no task id as a literal in the product's code (a special case for one task is a missing general
mechanism)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from dojo.compiler.spec_library import SpecLibrary

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"dojo": "dojo", "xpolicylab": "xpolicylab"}
# The concerns of the code base, one package each (dojo/<name>/); a new top-level folder is a design decision.
CONCERNS = {"backends", "bench", "cli", "compiler", "datagen", "evaluation", "experts", "language", "launch",
            "realeval", "report", "strict"}
ENGINES = ("MujocoBackend", "MjxBackend", "RealBackend")


def _modules() -> dict[str, Path]:
    out = {}
    for folder, package in PACKAGES.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            if "templates" in path.parts:
                continue
            rel = path.relative_to(ROOT / folder).with_suffix("").parts
            rel = rel[:-1] if rel[-1] == "__init__" else rel
            out[".".join((package, *rel))] = path
    return out


def _module_level_imports(name: str, path: Path, known: dict[str, Path]) -> set[str]:
    base = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    deps: set[str] = set()
    for node in ast.parse(path.read_text()).body:
        body = [node]
        if isinstance(node, ast.If):  # `if TYPE_CHECKING:` imports are for annotations only
            body = [] if isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING" else node.body
        for n in body:
            if isinstance(n, ast.Import):
                deps.update(a.name for a in n.names)
            elif isinstance(n, ast.ImportFrom):
                module = n.module or ""
                if n.level:
                    anchor = base
                    for _ in range(n.level - 1):
                        anchor = anchor.rsplit(".", 1)[0]
                    module = f"{anchor}.{module}" if module else anchor
                deps.add(module)
                deps.update(f"{module}.{a.name}" for a in n.names if f"{module}.{a.name}" in known)
    return {d for d in deps if d in known and d != name}


def test_import_paths_are_file_paths():
    """Every package under dojo/ is installed under its own path, and pyproject lists exactly those packages."""
    import tomllib

    import dojo

    assert Path(dojo.__file__).resolve() == ROOT / "dojo" / "__init__.py"
    folders = {p.parent for p in (ROOT / "dojo").rglob("__init__.py") if "__pycache__" not in p.parts}
    assert {f.name for f in folders if f.parent == ROOT / "dojo"} == CONCERNS
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    expected = {".".join(f.relative_to(ROOT).parts) for f in folders} | {"dojo.specs", "dojo.assets", "xpolicylab"}
    assert listed == expected


def test_no_import_cycle_at_module_level():
    known = _modules()
    graph = {name: _module_level_imports(name, path, known) for name, path in known.items()}
    state: dict[str, int] = {}
    cycles: list[list[str]] = []

    def visit(node: str, trail: list[str]) -> None:
        state[node] = 1
        for dep in sorted(graph[node]):
            if state.get(dep) == 1:
                cycles.append(trail[trail.index(dep):] + [dep])
            elif dep not in state:
                visit(dep, trail + [dep])
        state[node] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name, [name])
    assert not cycles, "\n".join(" -> ".join(c) for c in cycles)


def test_engines_are_built_only_by_their_own_package():
    pattern = re.compile(rf"\b({'|'.join(ENGINES)})\(")
    offenders = []
    for name, path in _modules().items():
        own = name.split(".")[:3]  # dojo.backends.<name>
        for line_no, line in enumerate(path.read_text().splitlines(), 1):
            match = pattern.search(line)
            if match and not line.lstrip().startswith(("class ", "#")):
                owner = {"MujocoBackend": "mujoco", "MjxBackend": "mjx", "RealBackend": "real"}[match.group(1)]
                if own != ["dojo", "backends", owner]:
                    offenders.append(f"{path.relative_to(ROOT)}:{line_no}: {line.strip()}")
    assert not offenders, "build engines with dojo.backends.registry.make_backend:\n" + "\n".join(offenders)


def test_no_task_id_literal_outside_tests():
    ids = {spec.id for spec in SpecLibrary.load().of_kind("task")}
    pattern = re.compile(r"""["'](%s)["']""" % "|".join(sorted(map(re.escape, ids), key=len, reverse=True)))
    offenders = []
    for path in _modules().values():
        for line_no, line in enumerate(path.read_text().splitlines(), 1):
            if pattern.search(line):
                offenders.append(f"{path.relative_to(ROOT)}:{line_no}: {line.strip()}")
    assert not offenders, "task ids written in product code (make it data):\n" + "\n".join(offenders)
