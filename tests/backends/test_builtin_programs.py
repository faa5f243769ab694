"""Every built-in task's program resolves against its compiled plan, and no task is won at its initial state."""

from __future__ import annotations

import numpy as np
import pytest
from dojo.backends.predicate_program import compile_program, init_memory, program_step, stack_params
from dojo.backends.predicate_state import mujoco_state
from dojo.compiler.plan import compile_plan
from dojo.compiler.spec_library import SpecLibrary


def builtin_tasks() -> list[str]:
    library = SpecLibrary.load([], strict=False)  # a task being written elsewhere must not hide the others
    return sorted(s.id for s in library.of_kind("task") if s.package == "builtin")


@pytest.mark.parametrize("task", builtin_tasks())
def test_builtin_program_compiles_and_starts_unsolved(library, task):
    plan = compile_plan(library, library.get("task", task), "standard", 0)
    program = compile_program(plan)
    state = mujoco_state(program.index, program.params["const_pos"], plan.initial_data())
    _, out = program_step(np, program.layout, state, stack_params([program.params]),
                          init_memory(np, program.layout, 1), 1)
    assert not out.success[0], f"{task} counts as solved before the robot moved"
    assert len(program.layout.stage_names) == len(plan.program.get("stages", []))
