"""Error values for spec loading.

Every problem found in a spec file becomes one `SpecProblem` that knows its file, line, column and JSON path,
so the CLI can print all of them at once as `file:line:col: $.json.path: message`, and so tests can assert the
exact location of each. Loading never raises on the first problem: it gathers them and raises one `SpecError`.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

JsonPath = tuple[str | int, ...]


def format_json_path(path: JsonPath) -> str:
    """`("scene", "objects", 2, "asset")` -> `$.scene.objects[2].asset` (the path users see in errors)."""
    out = "$"
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else f".{part}"
    return out


def closest(word: str, candidates: Iterable[str]) -> str | None:
    """The most similar candidate, if any is similar enough to be a plausible typo of `word`."""
    matches = difflib.get_close_matches(word, sorted(set(candidates)), n=1, cutoff=0.6)
    return matches[0] if matches else None


def did_you_mean(word: str, candidates: Iterable[str]) -> str:
    """A ` (did you mean 'x'?)` suffix, or nothing when no candidate is close."""
    match = closest(word, candidates)
    return f" (did you mean '{match}'?)" if match else ""


@dataclass(frozen=True)
class SpecProblem:
    """One problem at one place in one spec file. `safety` marks a breach of the rules that keep specs data
    (custom tags, code keys, interpolations, paths leaving the package, size bounds): `dojo validate --strict`
    reports those under its safety check, the rest under the schema check."""

    file: str
    line: int
    column: int
    path: JsonPath
    message: str
    safety: bool = False

    def __str__(self) -> str:
        return f"{self.file}:{self.line}:{self.column}: {format_json_path(self.path)}: {self.message}"

    def as_dict(self) -> dict:
        return {
            "file": self.file,
            "line": self.line,
            "column": self.column,
            "path": format_json_path(self.path),
            "message": self.message,
        }


class SpecError(Exception):
    """One or more problems in spec files; `str()` lists them all, one per line."""

    def __init__(self, problems: list[SpecProblem]):
        self.problems = sorted(problems, key=lambda p: (p.file, p.line, p.column, p.message))
        super().__init__("\n".join(str(p) for p in self.problems))

    def __reduce__(self) -> tuple:
        # Crosses process boundaries intact (parallel compilation re-raises a worker's error in the parent).
        return type(self), (self.problems,)


def display_path(path: Path) -> str:
    """Paths in messages are relative to the working directory when possible: shorter and clickable."""
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)
