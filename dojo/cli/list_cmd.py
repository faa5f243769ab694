"""`dojo list tasks|assets|robots|suites`: what is installed, as a table (or JSON for scripts)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Callable

from rich.console import Console
from rich.table import Table

from dojo.compiler.spec_errors import did_you_mean
from dojo.compiler.spec_library import Spec, SpecLibrary

EXAMPLE = "dojo list tasks --pack my_pack/"


def _names(values: object) -> str:
    return ", ".join(map(str, values)) if isinstance(values, list) else "" if values is None else str(values)


COLUMNS: dict[str, list[tuple[str, Callable[[Spec], str]]]] = {
    "task": [("id", lambda s: s.id), ("dimension", lambda s: s.data["dimension"]),
             ("embodiment", lambda s: s.data["embodiment"]), ("title", lambda s: s.data.get("title", "")),
             ("package", lambda s: s.package)],
    "asset": [("id", lambda s: s.id), ("class", lambda s: str(s.data.get("class", ""))),
              ("category", lambda s: str(s.data.get("category", ""))), ("names", lambda s: _names(s.data.get("names"))),
              ("sets", lambda s: _names(s.data.get("sets"))), ("package", lambda s: s.package)],
    "robot": [("id", lambda s: s.id), ("title", lambda s: str(s.data.get("title", ""))),
              ("source", lambda s: str(s.data.get("source", ""))[:60]), ("package", lambda s: s.package)],
    "suite": [("id", lambda s: s.id), ("tasks", lambda s: str(len(s.data["tasks"]))),
              ("episodes", lambda s: str(s.data.get("episodes", 50))), ("seeds", lambda s: _names(s.data.get("seeds"))),
              ("package", lambda s: s.package)],
}
PLURALS = {f"{k}s": k for k in COLUMNS}


def list_main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="dojo list", description="List the installed tasks, assets, robots or suites (built-in, plus packs).",
        epilog=f"example:\n  {EXAMPLE}", formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", help="tasks | assets | robots | suites")
    parser.add_argument("--pack", type=Path, action="append", default=[], help="also list this task pack's specs")
    parser.add_argument("--format", choices=("table", "json"), default="table")
    try:
        args = parser.parse_args(argv)
    except SystemExit as stop:
        return 0 if stop.code == 0 else 2
    kind = PLURALS.get(args.what) or (args.what if args.what in COLUMNS else None)
    if kind is None:
        print(f"dojo list: unknown kind '{args.what}'{did_you_mean(args.what, PLURALS)}; "
              f"one of {', '.join(PLURALS)}", file=sys.stderr)
        return 2
    library = SpecLibrary.load(args.pack, strict=False)
    specs = library.of_kind(kind)
    columns = COLUMNS[kind]
    if args.format == "json":
        print(json.dumps([{name: get(s) for name, get in columns} for s in specs]))
    else:
        table = Table(title=f"{len(specs)} {args.what}")
        for name, _ in columns:
            table.add_column(name)
        for spec in specs:
            table.add_row(*(get(spec) for _, get in columns))
        # Piped output is read by people too: do not squeeze it into 80 columns.
        Console(width=None if sys.stdout.isatty() else 200).print(table)
    if library.problems:
        print(f"dojo list: {len(library.problems)} spec problem(s) hid some entries; run dojo validate",
              file=sys.stderr)
    return 0
