"""Plans carry their success program resolved once, at compile time: a backend loads it bit-identical to a fresh
resolution, and a predicate that does not resolve against the scene is a located error of `dojo compile`."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from dojo.backends.predicate_program import compile_program, resolve_program
from dojo.backends.program_json import program_from_json, program_to_json
from dojo.compiler.plan import Plan, compile_plan
from dojo.compiler.spec_errors import SpecError
from dojo.compiler.spec_library import SpecLibrary

PACK = Path(__file__).parents[1] / "specs" / "pack"


@pytest.fixture(scope="module")
def library() -> SpecLibrary:
    return SpecLibrary.load([PACK])


def test_the_stored_program_is_the_resolved_one_bit_for_bit(library, tmp_path):
    plan = compile_plan(library, library.get("task", "stack_test"), "random", 2)
    plan.save(tmp_path / "plan.json")
    loaded = compile_program(Plan.load(tmp_path / "plan.json"))
    fresh = resolve_program(plan)
    assert loaded.layout == fresh.layout and loaded.index == fresh.index
    assert loaded.params.keys() == fresh.params.keys()
    for key, value in fresh.params.items():
        assert loaded.params[key].dtype == value.dtype and np.array_equal(loaded.params[key], value), key
    assert program_to_json(program_from_json(plan.compiled_program)) == plan.compiled_program


def test_a_predicate_the_scene_cannot_resolve_fails_at_compile_time_located(tmp_path):
    shutil.copytree(PACK, tmp_path / "pack")
    task = tmp_path / "pack" / "tasks" / "stack_test.yaml"
    text = task.read_text().replace("  - {name: placed, when: {on: [block, plate]}, weight: 2}",
                                    "  - {name: placed, when: {inside: [block, plate/nowhere]}, weight: 2}")
    task.write_text(text)
    library = SpecLibrary.load([tmp_path / "pack"])  # names check out: only the scene can tell
    with pytest.raises(SpecError) as info:
        compile_plan(library, library.get("task", "stack_test"), "standard", 0)
    line = text.splitlines().index("  - {name: placed, when: {inside: [block, plate/nowhere]}, weight: 2}") + 1
    message = str(info.value)
    assert f"stack_test.yaml:{line}:" in message and "no annotation 'nowhere'" in message, message
