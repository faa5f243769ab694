"""A plan file is read once per process while its plan is held: the batched backend's `preload` and the run loop
get the same object, and a changed file, or one nothing holds any more, is read again."""

from __future__ import annotations

import gc
import os
import weakref
from pathlib import Path

import pytest
from dojo.compiler.plan import Plan, compile_plan
from dojo.compiler.spec_library import SpecLibrary

PACK = Path(__file__).parents[1] / "specs" / "pack"


@pytest.fixture(scope="module")
def saved(tmp_path_factory) -> Path:
    library = SpecLibrary.load([PACK])
    path = tmp_path_factory.mktemp("plans") / "plan.json"
    compile_plan(library, library.get("task", "stack_test"), "random", 2).save(path)
    return path


def test_two_loads_of_one_file_share_the_plan_and_its_model(saved):
    first = Plan.load(saved)
    assert Plan.load(saved) is first
    assert Plan.load(Path(os.path.relpath(saved))) is first  # the same file by another spelling of its path
    assert Plan.load(str(saved)).model() is first.model()


def test_a_changed_file_is_read_again(saved, tmp_path):
    copy = tmp_path / "plan.json"
    copy.write_bytes(saved.read_bytes())
    first = Plan.load(copy)
    edited = tmp_path / "edited.json"
    edited.write_text(copy.read_text().replace(f'"horizon":{first.horizon},', f'"horizon":{first.horizon + 1},', 1))
    edited.replace(copy)  # as `Plan.save` writes: at once after the first read, same size, a new file
    changed = Plan.load(copy)
    assert changed is not first and changed.horizon == first.horizon + 1


def test_a_plan_nothing_holds_is_not_kept(saved):
    ref = weakref.ref(Plan.load(saved))
    gc.collect()
    assert ref() is None
    assert Plan.load(saved).hash  # and it loads again


def test_a_file_that_is_not_a_plan_is_refused_each_time(tmp_path):
    bad = tmp_path / "plan.json"
    bad.write_text('{"format": "something-else/1"}')
    for _ in range(2):
        with pytest.raises(ValueError, match="not a robodojo-plan/1 file"):
            Plan.load(bad)
