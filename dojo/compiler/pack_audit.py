"""What a task contribution is made of, for `dojo validate --strict`: a pack's tasks, their files, the settings
they are evaluated in, the pack's own assets each may draw, and the loader's problems sorted into the schema and
safety checks.

A pack's task is reported even when its file did not load (a code-injection attempt is refused by the YAML reader
before the file is known to be a task): every spec file of the pack that is a task, or whose kind could not be
read, is one row of the contribution report, named by its file stem. Assets a task may use are found by the same
function that hashes plans (`plan.input_specs`), so the audit checks exactly what a plan can contain.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from dojo.compiler.plan import input_specs
from dojo.compiler.spec_errors import SpecProblem, display_path
from dojo.compiler.spec_library import Spec, SpecLibrary, spec_files
from dojo.compiler.taxonomy import taxonomy_of

UNLOADED_KINDS = ("task", "unreadable", "unknown")
"""Kinds of a file that did not load and is still a row of the report: a task, or a file that may have been one."""


@dataclass(frozen=True)
class Finding:
    """One thing a check found, as a person reads it (file:line:col first when it has a place). An error fails
    the check; a warning is reported and lets it pass."""

    message: str
    warning: bool = False


@dataclass(frozen=True)
class PackTask:
    """One task of a pack, loaded (`spec`) or not (its file's problems say why)."""

    pack: Path
    task_id: str
    file: Path
    spec: Spec | None

    @property
    def display(self) -> str:
        return display_path(self.file)


def pack_tasks(library: SpecLibrary, pack: Path) -> list[PackTask]:
    """The tasks defined by the spec files under `pack`, in file order (loaded or not)."""
    by_file = {spec.path.resolve(): spec for spec in library.of_kind("task")}
    kinds = {file.resolve(): kind for file, kind in library.kind_of_file.items()}
    out = []
    for file in spec_files(pack):
        spec = by_file.get(file.resolve())
        if spec is not None:
            out.append(PackTask(pack, spec.id, file, spec))
        elif kinds.get(file.resolve()) in UNLOADED_KINDS:
            out.append(PackTask(pack, file.stem, file, None))
    return out


def file_problems(library: SpecLibrary, file: Path, *, safety: bool) -> list[SpecProblem]:
    """The loader's problems located in `file`: those breaching the safety rules, or the others."""
    display = display_path(file)
    return [p for p in library.problems if p.file == display and p.safety == safety]


def other_pack_files(library: SpecLibrary, pack: Path) -> list[Path]:
    """The pack's spec files that are not task rows (assets, suites, taxonomies): checked once for the pack."""
    rows = {t.file.resolve() for t in pack_tasks(library, pack)}
    return [f for f in spec_files(pack) if f.resolve() not in rows]


def protocol_settings(library: SpecLibrary, task: Spec) -> list[str]:
    """The settings the protocol evaluates a task in: both compared ones for a dimension that compares two
    (RoboDojo's Generalization: standard and random), else standard."""
    return list(taxonomy_of(library).compare_settings(task.data["dimension"]) or ["standard"])


def own_assets(library: SpecLibrary, task: Spec) -> list[Spec]:
    """The assets of the task's own package that any plan of the task may contain (the built-in ones are checked
    when the built-in package itself is validated)."""
    found: dict[str, Spec] = {}
    for setting in protocol_settings(library, task):
        for spec in input_specs(library, task, setting):
            if spec.kind == "asset" and spec.package == task.package:
                found.setdefault(spec.id, spec)
    return sorted(found.values(), key=lambda s: s.id)
