"""Loading whole spec packages and resolving the references between specs.

A *package* is a folder tree of spec files (`*.yaml`). The built-in package is `specs/` plus `assets/`; a
third-party task pack is any other folder. A reference resolves inside its own package first and then in the
built-in package (a pack may use the built-in robots and assets, never another pack's files). Loading gathers
every problem of every file before failing, so `dojo validate` reports them all at once.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any, Iterable

from dojo.compiler.spec_errors import JsonPath, SpecError, SpecProblem, did_you_mean, display_path
from dojo.compiler.spec_schema import SPEC_KINDS, RefUse, validate_spec_data
from dojo.compiler.spec_yaml import Located, read_spec_yaml
from dojo.compiler.task_checks import task_problems
from dojo.compiler.taxonomy import taxonomy_of

SINGLE_TARGET_KINDS = ("robot", "suite", "task")


@dataclass
class Spec:
    """One valid spec file: its data as plain Python values, and where it came from."""

    kind: str
    id: str
    data: dict
    path: Path
    display: str
    package: str
    package_root: Path
    located: Located
    refs: list[RefUse] = field(default_factory=list)

    def problem(self, path: JsonPath, message: str, *, key: bool = False) -> SpecProblem:
        """A problem located at `path` inside this spec (for checks made after schema validation)."""
        line, col = self.located.locate(path, key=key)
        return SpecProblem(self.display, line, col, path, message)


def builtin_roots() -> list[Path]:
    """The folders of the built-in package, wherever the distribution is installed."""
    return [Path(str(resources.files("dojo.specs"))), Path(str(resources.files("dojo.assets")))]


def spec_files(root: Path) -> list[Path]:
    """Spec files under `root` (or `root` itself), in a stable order. Hidden folders are skipped."""
    if root.is_file():
        return [root]
    found = [p for p in root.rglob("*") if p.suffix in (".yaml", ".yml") and p.is_file()]
    return sorted(p for p in found if not any(part.startswith(".") for part in p.relative_to(root).parts))


def load_spec_file(path: Path, package: str, package_root: Path) -> tuple[Spec | None, list[SpecProblem], str]:
    """Read, check and validate one file: the spec (or None), its problems, and its kind as far as it is known
    (`unreadable` when the file could not be parsed, `unknown` when it names no valid kind)."""
    display = display_path(path)
    located, problems = read_spec_yaml(path, display)
    if located is None:
        return None, problems, "unreadable"
    data = located.data
    if not isinstance(data, dict):
        line, col = located.locate(())
        return None, [SpecProblem(display, line, col, (), "a spec is a mapping with at least kind, version and id")], "unknown"
    kind = data.get("kind")
    if kind not in SPEC_KINDS:
        line, col = located.locate(("kind",))
        message = (f"missing required field 'kind' (one of {', '.join(SPEC_KINDS)})" if kind is None else
                   f"unknown kind {kind!r}; one of {', '.join(SPEC_KINDS)}{did_you_mean(str(kind), SPEC_KINDS)}")
        return None, [SpecProblem(display, line, col, ("kind",) if kind is not None else (), message)], "unknown"
    problems, refs = validate_spec_data(kind, located, display, path.parent, package_root)
    if not problems and path.stem != data["id"]:
        line, col = located.locate(("id",))
        problems = [SpecProblem(display, line, col, ("id",),
                                f"id '{data['id']}' must match the file name '{path.stem}' (so specs can be found by id)")]
    if problems:
        return None, problems, kind
    return Spec(kind, data["id"], data, path, display, package, package_root, located, refs), [], kind


class SpecLibrary:
    """Every spec of the loaded packages, indexed by (package, kind, id), with reference resolution."""

    def __init__(self) -> None:
        self.specs: list[Spec] = []
        self._index: dict[tuple[str, str, str], Spec] = {}
        self.problems: list[SpecProblem] = []
        self.kind_of_file: dict[Path, str] = {}
        # (package, file stem) -> (kind as far as known, display path) of files that did not load: a reference to
        # one of them is reported as such, not as an unknown id that hides the file's own problem.
        self._invalid: dict[tuple[str, str], tuple[str, str]] = {}

    @classmethod
    def load(cls, packages: Iterable[Path] = (), *, builtin: bool = True, strict: bool = True) -> "SpecLibrary":
        """Load the built-in package and the given package folders (or files).

        With `strict`, any problem raises a `SpecError` listing all of them; otherwise the problems are kept in
        `.problems` and the valid specs stay usable (what `dojo validate` reports).
        """
        lib = cls()
        if builtin:
            for root in builtin_roots():
                lib._add_package("builtin", root, root)
        for path in packages:
            path = Path(path)
            if not path.exists():
                lib.problems.append(SpecProblem(str(path), 1, 1, (), "no such file or folder"))
                continue
            root = path if path.is_dir() else path.parent
            if builtin and any(_within(path, b) for b in builtin_roots()):
                continue  # already loaded as part of the built-in package
            lib._add_package(display_path(root), path, root)
        lib._check_references()
        if strict and lib.problems:
            raise SpecError(lib.problems)
        return lib

    def _add_package(self, package: str, path: Path, root: Path) -> None:
        for file in spec_files(path):
            if package == "builtin":
                stat = file.stat()
                spec, problems, kind = _load_builtin_file(file, root, stat.st_mtime_ns, stat.st_size)
            else:
                spec, problems, kind = load_spec_file(file, package, root)
            self.kind_of_file[file] = kind
            self.problems.extend(problems)
            if spec is None:
                self._invalid.setdefault((package, file.stem), (kind, display_path(file)))
                continue
            key = (package, spec.kind, spec.id)
            if key in self._index:
                first = self._index[key]
                line, _ = first.located.locate(("id",))
                self.problems.append(spec.problem(("id",), f"duplicate {spec.kind} id '{spec.id}' "
                                                           f"(also defined at {first.display}:{line})"))
                continue
            if package != "builtin" and ("builtin", spec.kind, spec.id) in self._index:
                # A pack's spec with a built-in id would make every reference to that id ambiguous.
                self.problems.append(spec.problem(("id",), f"ambiguous {spec.kind} id '{spec.id}': a built-in "
                                                           f"{spec.kind} has it already; choose another id"))
                continue
            self._index[key] = spec
            self.specs.append(spec)

    def of_kind(self, kind: str) -> list[Spec]:
        """Specs of one kind, built-in first, each package in file order."""
        return [s for s in self.specs if s.kind == kind]

    def get(self, kind: str, spec_id: str, *, package: str | None = None) -> Spec:
        """The spec of `kind` with `spec_id`: in `package` (then the built-in one) when given, else in whichever
        loaded package defines it (an id defined by two packs must then be asked for with its package)."""
        if package is not None:
            for pkg in dict.fromkeys((package, "builtin")):
                if (pkg, kind, spec_id) in self._index:
                    return self._index[(pkg, kind, spec_id)]
            found = []
        else:
            found = [s for s in self.of_kind(kind) if s.id == spec_id]
            if len(found) == 1:
                return found[0]
        if len(found) > 1:
            raise KeyError(f"{kind} '{spec_id}' is defined in several packages ({', '.join(s.package for s in found)})")
        known = [s.id for s in self.of_kind(kind)]
        raise KeyError(f"unknown {kind} '{spec_id}'{did_you_mean(spec_id, known)}")

    def resolve(self, owner: Spec, kind: str, ref: Any) -> list[Spec]:
        """The specs a reference names: one for an id, every match for a query. Raises `SpecError` if none."""
        problem = self._resolve_problem(owner, RefUse((), kind, ref))
        if problem:
            raise SpecError([problem])
        return self._candidates(owner.package, kind, ref)

    def _scope(self, package: str, kind: str) -> list[Spec]:
        own = [s for s in self.specs if s.kind == kind and s.package == package]
        return own + [s for s in self.specs if s.kind == kind and s.package == "builtin" and package != "builtin"]

    def _candidates(self, package: str, kind: str, ref: Any) -> list[Spec]:
        scope = self._scope(package, kind)
        if isinstance(ref, str):
            return [next(s for s in scope if s.id == ref)] if any(s.id == ref for s in scope) else []
        return [s for s in scope if _matches(s.data, ref)]

    def _resolve_problem(self, owner: Spec, use: RefUse) -> SpecProblem | None:
        found = self._candidates(owner.package, use.kind, use.value)
        scope = self._scope(owner.package, use.kind)
        if owner.kind == "suite" and use.kind == "task" and found:
            dimension = found[0].data.get("dimension")
            if dimension in taxonomy_of(self).training_only:
                return owner.problem(use.path, f"task '{found[0].id}' is training-only (dimension {dimension}): "
                                               "suites evaluate; demonstrate it with `dojo collect` instead")
        if isinstance(use.value, str):
            if not found:
                broken = self._invalid_file(owner.package, use.kind, use.value)
                if broken:
                    return owner.problem(use.path, f"{use.kind} '{use.value}' did not load: {broken} is invalid "
                                                   "(its problems are reported at that file)")
                hint = did_you_mean(use.value, [s.id for s in scope])
                return owner.problem(use.path, f"unknown {use.kind} '{use.value}'{hint}")
            return None
        if not found:
            hints = []
            for key, wanted in use.value.items():
                values = {str(v) for s in scope for v in _as_list(s.data.get(_FIELD.get(key, key)))}
                for item in _as_list(wanted):
                    if str(item) not in values:
                        hints.append(f"no {use.kind} has {key} '{item}'{did_you_mean(str(item), values)}")
            detail = "; ".join(hints) or "no single spec has all these fields"
            return owner.problem(use.path, f"no {use.kind} matches {_query_text(use.value)}: {detail}")
        if use.kind in SINGLE_TARGET_KINDS and len(found) > 1:
            names = ", ".join(s.id for s in found[:5])
            return owner.problem(use.path, f"query {_query_text(use.value)} is ambiguous: it matches {len(found)} "
                                           f"{use.kind}s ({names}); name one by id")
        return None

    def _invalid_file(self, package: str, kind: str, spec_id: str) -> str | None:
        """The file that would define `spec_id` in the owner's scope but did not load, if there is one."""
        for pkg in dict.fromkeys((package, "builtin")):
            found = self._invalid.get((pkg, spec_id))
            if found and found[0] in (kind, "unreadable", "unknown"):
                return found[1]
        return None

    def _check_references(self) -> None:
        for spec in self.specs:
            for use in spec.refs:
                problem = self._resolve_problem(spec, use)
                if problem:
                    self.problems.append(problem)
            if spec.kind == "task":
                for path, message, key in task_problems(spec.data):
                    self.problems.append(spec.problem(path, message, key=key))
        self._check_dimensions()
        self._check_suite_cycles()

    def _check_dimensions(self) -> None:
        """Every task's dimension is in the taxonomy; a pack adds dimensions but never redefines one."""
        seen: dict[str, Spec] = {}
        for spec in self.of_kind("taxonomy"):
            for i, dimension in enumerate(spec.data["dimensions"]):
                first = seen.setdefault(dimension["id"], spec)
                if first is not spec:
                    self.problems.append(spec.problem(("dimensions", i, "id"), f"dimension '{dimension['id']}' is "
                                                      f"defined already (taxonomy {first.id}, {first.display})"))
        known = taxonomy_of(self).ids
        for task in self.of_kind("task"):
            dimension = task.data["dimension"]
            if dimension not in known:
                self.problems.append(task.problem(("dimension",), f"unknown dimension '{dimension}'"
                                                  f"{did_you_mean(dimension, known)} (a pack adds dimensions with a "
                                                  "`kind: taxonomy` spec)"))

    def _check_suite_cycles(self) -> None:
        reported: set[frozenset[str]] = set()
        for suite in self.of_kind("suite"):
            stack: list[tuple[Spec, list[str]]] = [(suite, [suite.id])]
            while stack:
                current, trail = stack.pop()
                for i, child_id in enumerate(current.data.get("include", [])):
                    if child_id == suite.id:
                        cycle = frozenset(trail)
                        if cycle not in reported:
                            reported.add(cycle)
                            chain = " -> ".join(trail + [child_id])
                            self.problems.append(current.problem(("include", i), f"suite include cycle: {chain}"))
                        continue
                    if child_id in trail:
                        continue  # a cycle not through `suite`: reported when its own members are checked
                    child = self._candidates(current.package, "suite", child_id)
                    if child:
                        stack.append((child[0], trail + [child_id]))

    def suite_tasks(self, suite: Spec) -> list[tuple[Spec, dict]]:
        """The suite's task entries with includes expanded (first occurrence wins), as (task spec, entry)."""
        out: dict[str, tuple[Spec, dict]] = {}
        seen: set[str] = set()

        def visit(s: Spec) -> None:
            if s.id in seen:
                return
            seen.add(s.id)
            for included in s.data.get("include", []):
                visit(self.resolve(s, "suite", included)[0])
            for entry in s.data["tasks"]:
                entry = {"task": entry} if isinstance(entry, str) else dict(entry)
                task = self.resolve(s, "task", entry["task"])[0]
                out.setdefault(task.id, (task, entry))

        visit(suite)
        return list(out.values())


@lru_cache(maxsize=4096)
def _load_builtin_file(file: Path, root: Path, mtime_ns: int, size: int) -> tuple[Spec | None, list[SpecProblem], str]:
    """Built-in specs are read once per process (keyed by modification time and size, so an edit is seen):
    every library load includes them, and they are never modified in memory."""
    return load_spec_file(file, "builtin", root)


_FIELD = {"set": "sets"}


def _as_list(value: Any) -> list:
    return value if isinstance(value, list) else [] if value is None else [value]


def _matches(data: dict, query: dict) -> bool:
    """Does a spec's data satisfy a query? List-valued fields (tags, sets) must contain every wanted value."""
    for key, wanted in query.items():
        have = data.get(_FIELD.get(key, key))
        if isinstance(have, list):
            if not set(_as_list(wanted)) <= set(have):
                return False
        elif have != wanted:
            return False
    return True


def _query_text(query: dict) -> str:
    return "{" + ", ".join(f"{k}: {v}" for k, v in query.items()) + "}"


def _within(path: Path, root: Path) -> bool:
    path, root = path.resolve(), root.resolve()
    return path == root or root in path.parents
