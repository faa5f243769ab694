"""Named success terms: the program names each condition of a task's success predicate, the CPU backend reports
them every step, the episode row keeps them, the store migrates older files to hold them, and the report says
which condition failed episodes missed."""

from __future__ import annotations

import dataclasses
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from dojo.backends.predicate_program import resolve_program
from dojo.backends.registry import BackendOptions, make_backend
from dojo.compiler.plan import compile_plan
from dojo.compiler.spec_library import SpecLibrary
from dojo.report.make_report import build_report
from dojo.evaluation.results_store import SCHEMA_VERSION, ResultsStore

PACK = Path(__file__).parents[1] / "specs" / "pack"


@pytest.fixture(scope="module")
def plan():
    library = SpecLibrary.load([PACK])
    return compile_plan(library, library.get("task", "stack_test"), "standard", 0)


def test_the_terms_of_a_conjunction_are_its_conditions(plan):
    two = dataclasses.replace(plan, compiled_program={}, program={
        **plan.program, "success": {"all": [{"on": ["block", "plate"]}, {"upright": "block"}]}})
    layout = resolve_program(two).layout
    assert layout.term_names == ("on(block, plate)", "upright(block)")
    assert resolve_program(plan).layout.term_names == ("on(block, plate)",)  # a single predicate is one term


def test_the_cpu_backend_reports_each_term_every_step(plan):
    two = dataclasses.replace(plan, compiled_program={}, program={
        **plan.program, "success": {"all": [{"on": ["block", "plate"]}, {"upright": "block"}]}})
    with make_backend("mujoco", BackendOptions(settings={"threads": 1})) as backend:
        backend.load([two])
        backend.reset()
        result = backend.step(np.zeros((1, 14), np.float32), [0])
    assert result.terms == [{"on(block, plate)": False, "upright(block)": True}]


def test_rows_keep_terms_old_stores_migrate_and_the_report_names_unmet_conditions(tmp_path, make_task_rows):
    path = tmp_path / "results.sqlite"
    rows = make_task_rows("stack_test", "precision", [(False, 10.0), (False, 20.0), (True, 100.0)])
    rows = [dataclasses.replace(r, success_terms={"on(block, plate)": r.success, "upright(block)": True})
            for r in rows]
    with ResultsStore(path) as store:
        store.add_many(rows[:1])
    db = sqlite3.connect(path)  # make it a store of the previous schema, as last month's runs are
    db.execute("ALTER TABLE episodes DROP COLUMN success_terms")
    db.execute("ALTER TABLE episodes DROP COLUMN counters")  # schema 3's column, added after schema 1
    db.execute("ALTER TABLE episodes DROP COLUMN backend")  # schema 4's
    db.execute("UPDATE meta SET value = '1' WHERE key = 'schema_version'")
    db.commit()
    db.close()
    with ResultsStore(path, readonly=True) as old:  # a reader reads it as it is
        assert [r.success_terms for r in old.rows()] == [{}]
    with ResultsStore(path) as store:  # a writer migrates it, and resumes into it
        store.add_many(rows[1:])
        stored = store.rows()
    assert sqlite3.connect(path).execute("SELECT value FROM meta").fetchone()[0] == str(SCHEMA_VERSION)
    assert [r.success_terms for r in stored][1:] == [r.success_terms for r in rows[1:]]
    entry = build_report(stored)["entries"][0]
    assert entry["unmet_conditions"] == {"stack_test": {"on(block, plate)": 1}}
