"""The contribution report of `dojo validate --strict`: a table on the terminal, JSON, and JUnit XML, all from the
same rows of check results.

JUnit is for a contributor's own CI: GitHub Actions (and most CI systems) show each `<testcase>` of a JUnit file,
so each (task, check) is one test case, named `<check>` in class `<pack>.<task>`: a failed check is a `<failure>`
whose message is its first finding, a check not run is `<skipped>`, and warnings are kept in `<system-out>`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any
from xml.etree import ElementTree as ET

from rich.console import Console
from rich.table import Table
from rich.text import Text

from dojo.strict.checks import PACK_CHECKS, TASK_CHECKS, Audit

STYLE = {"pass": ("pass", "green"), "warn": ("warn", "yellow"), "fail": ("FAIL", "bold red"),
         "skip": ("skip", "dim")}


def passed(rows: Sequence[Audit]) -> bool:
    """Every row passed every check it ran (warnings pass): the exit code is 0 exactly then."""
    return not any(row.failed for row in rows)


def summary(rows: Sequence[Audit]) -> str:
    tasks = [row for row in rows if row.task is not None]
    failed = [row for row in rows if row.failed]
    packs = len({row.pack for row in rows})
    verdict = "every check passed" if not failed else (
        f"{len(failed)} row(s) failed: " + ", ".join(f"{row.name} ({_first_failure(row)})" for row in failed))
    return f"{len(tasks)} task(s) in {packs} pack(s): {verdict}"


def _first_failure(row: Audit) -> str:
    return next(r.check for r in row.results if r.status == "fail")


def print_table(rows: Sequence[Audit], console: Console) -> None:
    """The table (task, check, result, figure), then every finding of a failed or warning check, then the verdict."""
    table = Table(show_lines=False, header_style="bold")
    for column in ("task", "check", "result", "figure"):
        table.add_column(column, overflow="fold")
    for row in rows:
        for i, result in enumerate(row.results):
            label, style = STYLE[result.status]
            name = (row.name if row.task else f"{row.file} (pack)") if i == 0 else ""
            table.add_row(name, result.check, Text(label, style=style), result.figure,
                          end_section=i == len(row.results) - 1)
    console.print(table)
    for row in rows:
        for result in row.results:
            for finding in result.findings:
                label, style = ("warning", "yellow") if finding.warning else ("error", "red")
                line = Text.assemble((f"{row.name} {result.check} {label}: ", style), finding.message)
                console.print(line, soft_wrap=True)
    console.print(Text(summary(rows), style="bold green" if passed(rows) else "bold red"))


def report_json(rows: Sequence[Audit], *, seeds: int, jobs: int, wall_s: float) -> dict[str, Any]:
    """The whole report as plain data (`--format json`)."""
    return {
        "valid": passed(rows), "seeds": seeds, "jobs": jobs, "wall_s": round(wall_s, 1),
        "checks": [{"check": c.name, "proves": c.proves} for c in TASK_CHECKS],
        "rows": [{
            "pack": str(row.pack), "task": row.name if row.task else None, "file": row.file,
            "passed": not row.failed,
            "checks": [{"check": r.check, "status": r.status, "figure": r.figure, "seconds": round(r.seconds, 2),
                        "findings": [{"level": "warning" if f.warning else "error", "message": f.message}
                                     for f in r.findings]} for r in row.results],
        } for row in rows],
    }


def junit_xml(rows: Sequence[Audit], *, wall_s: float) -> str:
    """JUnit XML: one <testsuite> per pack, one <testcase> per (row, check)."""
    proves = {c.name: c.proves for c in TASK_CHECKS}
    pack_proves = {c.name: c.proves for c in PACK_CHECKS}
    root = ET.Element("testsuites", name="dojo validate --strict", time=f"{wall_s:.1f}")
    totals = {"tests": 0, "failures": 0, "skipped": 0}
    for pack in dict.fromkeys(row.pack for row in rows):
        suite = ET.SubElement(root, "testsuite", name=str(pack))
        counts = {"tests": 0, "failures": 0, "skipped": 0}
        for row in (r for r in rows if r.pack == pack):
            classname = f"{pack}.{row.name if row.task else 'pack'}"
            for result in row.results:
                case = ET.SubElement(suite, "testcase", classname=classname, name=result.check,
                                     time=f"{result.seconds:.2f}", file=row.file)
                counts["tests"] += 1
                errors = [f.message for f in result.findings if not f.warning]
                warnings = [f.message for f in result.findings if f.warning]
                if result.status == "fail":
                    counts["failures"] += 1
                    failure = ET.SubElement(case, "failure", message=errors[0] if errors else result.figure)
                    failure.text = "\n".join(errors)
                elif result.status == "skip":
                    counts["skipped"] += 1
                    ET.SubElement(case, "skipped", message=result.figure)
                out = ET.SubElement(case, "system-out")
                what = (proves if row.task else pack_proves).get(result.check, "")
                out.text = "\n".join([f"{result.check}: {what}", result.figure] + [f"warning: {w}" for w in warnings])
        for key, value in counts.items():
            suite.set(key, str(value))
            totals[key] += value
    for key, value in totals.items():
        root.set(key, str(value))
    ET.indent(root)
    return ET.tostring(root, encoding="unicode", xml_declaration=True) + "\n"
