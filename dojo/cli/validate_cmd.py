"""`dojo validate PATH...`: check spec files and packages, report every problem at once.

Exit codes are for scripts: 0 all valid, 1 some spec is invalid, 2 the command itself was misused (a path that
does not exist, a bad flag). The built-in package is always loaded so that a third-party pack can refer to the
built-in robots and assets; its problems are reported only when a built-in path is among those checked. With no
path, the built-in specs and assets themselves are checked (wherever the package is installed).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

from dojo.compiler.spec_library import SpecLibrary, builtin_roots, spec_files

EXAMPLE = "dojo validate specs/ my_pack/ --format json\n  dojo validate                 (the built-in specs and assets)"


def validate_main(argv: list[str]) -> int:
    if "--strict" in argv:  # a contribution's full audit: its own arguments (strict_cmd)
        from dojo.cli.strict_cmd import strict_main
        return strict_main(argv)
    parser = argparse.ArgumentParser(
        prog="dojo validate",
        description="Check spec files (tasks, assets, robots, suites) against the JSON Schemas, resolve their "
                    "references, and report every problem as file:line:col: $.path: message.",
        epilog=f"example:\n  {EXAMPLE}\n\nexit codes: 0 valid, 1 invalid, 2 usage error",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", nargs="*", type=Path,
                        help="spec files or folders (folders are searched for *.yaml); none: the built-in ones")
    parser.add_argument("--format", choices=("text", "json"), default="text", help="output format (default: text)")
    parser.add_argument("--strict", action="store_true",
                        help="also compile, simulate and run every task's expert, zero and random policies: the "
                             "full audit of a task contribution (see dojo validate --strict --help)")
    try:
        args = parser.parse_args(argv)
    except SystemExit as stop:
        return 0 if stop.code == 0 else 2
    args.paths = args.paths or builtin_roots()
    missing = [p for p in args.paths if not p.exists()]
    if missing:
        print(f"dojo validate: no such file or folder: {', '.join(map(str, missing))}", file=sys.stderr)
        return 2

    library = SpecLibrary.load(args.paths, strict=False)
    files = {f.resolve() for p in args.paths for f in spec_files(p)}
    kinds = Counter(kind for file, kind in library.kind_of_file.items() if file.resolve() in files)
    problems = [p for p in library.problems if Path(p.file).resolve() in files]
    bad_files = len({p.file for p in problems})

    if args.format == "json":
        print(json.dumps({"valid": not problems, "checked": dict(sorted(kinds.items())), "files": len(files),
                          "invalid_files": bad_files, "problems": [p.as_dict() for p in problems]}))
    else:
        for problem in problems:
            print(problem)
        counts = ", ".join(f"{n} {k}" for k, n in sorted(kinds.items())) or "nothing"
        verdict = "all valid" if not problems else f"{len(problems)} problem(s) in {bad_files} file(s)"
        print(f"checked {len(files)} spec file(s) ({counts}): {verdict}", file=sys.stderr if problems else sys.stdout)
    return 1 if problems else 0
