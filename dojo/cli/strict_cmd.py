"""`dojo validate --strict PACK...`: prove a contributed task pack sound before it is merged.

Every task of every pack is checked in order (schema, safety, asset, determinism, stability, solvability,
not_trivial, horizon; `dojo.strict.checks`), stopping a task at its first failure and never the pack. The report is a
table on the terminal, or JSON (`--format json`), and optionally JUnit XML (`--junit FILE`) for the contributor's
CI. Exit codes: 0 every task passed every check (warnings allowed), 1 some check failed, 2 the command was
misused (a path that does not exist, a bad flag).

Plans and results are kept by plan hash under `--cache` (default `$DOJO_PLAN_CACHE/strict`), so a re-run after a
fix redoes only the tasks the fix changed.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from rich.console import Console

from dojo.compiler.spec_library import SpecLibrary

from dojo.cli.run_cmd import DEFAULT_PLAN_CACHE
from dojo.strict.audit import audit_packs
from dojo.strict.report import junit_xml, passed, print_table, report_json

EXAMPLE = "dojo validate --strict my_pack/ --seeds 20 -j 4 --junit report.xml"


def strict_main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="dojo validate --strict",
        description="Check that every task of a pack is well-formed, safe, physically sane, deterministic, "
                    "stable, solvable by its scripted expert, not solved by zero or random actions, and that the "
                    "expert fits in the horizon (CPU backend). One row per task, one line per check.",
        epilog=f"example:\n  {EXAMPLE}\n\nexit codes: 0 every check passed, 1 some check failed, 2 usage error",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--strict", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("paths", nargs="+", type=Path, help="task pack folders (or `specs/` for the built-in tasks)")
    parser.add_argument("--seeds", type=int, default=20, help="scene seeds per task and setting (default: 20)")
    parser.add_argument("-j", "--jobs", type=int, default=os.cpu_count() or 1,
                        help="worker processes, one plan or episode each at a time (default: every core)")
    parser.add_argument("--format", choices=("text", "json"), default="text", help="output format (default: text)")
    parser.add_argument("--junit", type=Path, metavar="FILE", help="also write the report as JUnit XML to FILE")
    parser.add_argument("--cache", type=Path, default=DEFAULT_PLAN_CACHE / "strict",
                        help="where plans and results are kept by plan hash (default: %(default)s)")
    try:
        args = parser.parse_args(argv)
    except SystemExit as stop:
        return 0 if stop.code == 0 else 2
    missing = [p for p in args.paths if not p.exists()]
    if missing or args.seeds < 1 or args.jobs < 1:
        why = (f"no such file or folder: {', '.join(map(str, missing))}" if missing else
               "--seeds and --jobs must be at least 1")
        print(f"dojo validate --strict: {why}", file=sys.stderr)
        return 2

    start = time.monotonic()
    library = SpecLibrary.load(args.paths, strict=False)
    rows = audit_packs(library, args.paths, seeds=args.seeds, jobs=args.jobs, cache=args.cache,
                       console=Console(file=sys.stderr))
    wall = time.monotonic() - start
    if args.junit:
        args.junit.parent.mkdir(parents=True, exist_ok=True)
        args.junit.write_text(junit_xml(rows, wall_s=wall))
    if args.format == "json":
        print(json.dumps(report_json(rows, seeds=args.seeds, jobs=args.jobs, wall_s=wall)))
    else:
        console = Console(width=None if sys.stdout.isatty() else 160)  # CI logs: no wrapping at 80 columns
        print_table(rows, console)
        console.print(f"{args.seeds} seed(s) per setting, {args.jobs} job(s), {wall:.0f} s"
                      + (f"; JUnit: {args.junit}" if args.junit else ""))
    return 0 if passed(rows) else 1
