"""History words: pressed(..., exactly) counts presses exactly (an overshoot fails for good), at_start_of compares
with where an object was at the start of the episode, and facts become the episode's values in the plan."""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest
from dojo.backends.predicate_program import Press, ProgramLayout, compile_program, init_memory, program_step, stack_params
from dojo.backends.predicate_state import mujoco_state
from dojo.language.facts import FactError, resolve_facts
from dojo.language.predicates.pressed import Pressed


def _presses(qs: list[float], node: Pressed) -> list[bool]:
    lay = ProgramLayout(node, (), (), (), False, (Press(0, None),), 0)
    params = {"frame_c": np.zeros((1, 0, 3)), "frame_h": np.zeros((1, 0, 3)), "const_pos": np.zeros((1, 0, 3)),
              "init_center": np.zeros((1, 0, 3)), "press_rest": np.zeros((1, 1)),
              "press_far": np.full((1, 1), -0.01)}
    memory, out = init_memory(np, lay, 1), []
    for t, q in enumerate(qs, start=1):
        state = {"pos": np.zeros((1, 0, 3)), "mat": np.zeros((1, 0, 3, 3)), "qpos": np.array([[q]]),
                 "contact": np.zeros((1, 0, 0), bool)}
        memory, result = program_step(np, lay, state, params, memory, t)
        out.append(bool(result.success[0]))
    return out


def test_pressed_exactly_holds_only_at_the_count():
    downs = [0.0, -0.009, 0.0, -0.009, 0.0, -0.009, 0.0]  # three presses
    assert _presses(downs, Pressed(0, 2, exact=True)) == [False, False, False, True, True, False, False]
    assert _presses(downs, Pressed(0, 2)) == [False, False, False, True, True, True, True]


def test_at_start_of_compares_with_the_start_pose(probe_plan, set_free_pose):
    plan = dataclasses.replace(probe_plan, compiled_program={}, program={
        **probe_plan.program, "stages": [], "success": {"at_start_of": {"object": "cube_0", "of": "cube_1"}}})
    program = compile_program(plan, probe_plan.model())
    assert "init_mat" in program.params
    model = probe_plan.model()
    data = plan.initial_data(model)
    adr = model.joint("cube_1/free").qposadr[0]
    start, quat = data.qpos[adr:adr + 3].copy(), data.qpos[adr + 3:adr + 7].copy()
    memory = init_memory(np, program.layout, 1)

    def holds(d: mujoco.MjData) -> bool:
        state = mujoco_state(program.index, program.params["const_pos"], d)
        return bool(program_step(np, program.layout, state, stack_params([program.params]), memory, 1)[1].success[0])

    assert not holds(data)
    qpos = data.qpos.copy()
    set_free_pose(plan, qpos, "cube_1", [0.3, 0.3, 0.8])           # cube_1 leaves ...
    set_free_pose(plan, qpos, "cube_0", start, quat)               # ... and cube_0 takes its start pose
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    assert holds(data)
    turn = np.array([np.cos(np.radians(15)), 0.0, 0.0, np.sin(np.radians(15))])  # 30 degrees about z
    turned = np.zeros(4)
    mujoco.mju_mulQuat(turned, turn, quat)
    set_free_pose(plan, qpos, "cube_0", start, turned)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    assert not holds(data)  # beyond the default 10 degree tolerance


def test_facts_resolve_to_the_objects_attributes():
    objects = {"card": {"attributes": {"number": 3}}}
    pred = {"pressed": ["button", {"attribute": ["card", "number"]}, "exactly"]}
    assert resolve_facts(pred, objects) == {"pressed": ["button", 3, "exactly"]}
    with pytest.raises(FactError, match="no attribute 'digit'") as err:
        resolve_facts({"all": [pred, {"pressed": ["b", {"attribute": ["card", "digit"]}]}]}, objects, ("success",))
    assert err.value.path == ("success", "all", 1, "pressed", 1)
    with pytest.raises(FactError, match="no object 'deck'"):
        resolve_facts({"attribute": ["deck", "number"]}, objects)


def _sequence(qs: list[list[float]]) -> bool:
    """sequence([q0 >= 1, q1 >= 1]) after the joint states qs[t] = [q0, q1] of steps 1, 2, ..."""
    from dojo.language.predicates.joint_bound import JointBound
    from dojo.language.predicates.sequence import Sequence

    node = Sequence((JointBound(0, 1.0, True), JointBound(1, 1.0, True)), 0)
    lay = ProgramLayout(node, (), (), (), False, (), 4)
    params = {"frame_c": np.zeros((1, 0, 3)), "frame_h": np.zeros((1, 0, 3)), "const_pos": np.zeros((1, 0, 3)),
              "init_center": np.zeros((1, 0, 3)), "press_rest": np.zeros((1, 0)), "press_far": np.zeros((1, 0))}
    memory = init_memory(np, lay, 1)
    for t, q in enumerate(qs, start=1):
        state = {"pos": np.zeros((1, 0, 3)), "mat": np.zeros((1, 0, 3, 3)), "qpos": np.array([q], float),
                 "contact": np.zeros((1, 0, 0), bool)}
        memory, out = program_step(np, lay, state, params, memory, t)
    return bool(out.success[0])


def test_sequence_needs_each_to_turn_true_after_the_one_before():
    assert _sequence([[0, 0], [1, 0], [1, 1]])           # the first, then the second
    assert _sequence([[1, 0], [1, 1]])                   # the first may hold from the start
    assert _sequence([[1, 0], [0, 0], [0, 1]])           # the first need not hold any more
    assert not _sequence([[0, 1], [1, 1], [1, 1]])       # the second held before the first: it never turned after
    assert _sequence([[0, 1], [1, 0], [1, 1]])           # ... unless it turned false and true again after
    assert not _sequence([[0, 0], [0, 1], [1, 1]])       # the wrong order
