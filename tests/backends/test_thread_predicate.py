"""Threads (an asset's `threads:`, a hinge coupled to a slide by a joint equality) and `tightened(screw,
object/hinge, turns)`: the predicate on hand-built states (positive and negative), compiled against fasten_screws,
and the coupling simulated as the CPU backend does (MJX runs the same `equality:joint` rows)."""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np
import pytest
from dojo.backends.predicate_program import ProgramError, ProgramLayout, compile_program, init_memory, program_step
from dojo.compiler.plan import compile_plan
from dojo.compiler.spec_library import SpecLibrary
from dojo.language.predicates.connectives import AllOf
from dojo.language.predicates.tightened import Tightened

SOCKET = np.array([0.0, 0.0, 0.026])
"""The socket box's centre; it is 15 mm square and 16 mm deep (half 7.5, 7.5, 8 mm)."""
SCREW_C, SCREW_H = [0.0, 0.0, 0.02], [0.014, 0.014, 0.02]
"""The screw's box in its frame: 4 cm tall above its tip (the frame's origin)."""
NODE = Tightened(screw=0, socket=1, joint=0, rest=0.0, direction=1.0, angle=2.0 * math.pi)
"""A full turn of the hinge in qpos column 0, from rest 0 in the positive sense."""
FLOOR = SOCKET[2] - 0.008


def tightened(node: Tightened, tips: list[list[float]], angles: list[float]) -> list[bool]:
    """The node on one environment per (screw tip position, hinge angle); the socket box stays at SOCKET."""
    n = len(tips)
    pos = np.stack([np.stack([np.asarray(t, float), SOCKET]) for t in tips])
    state = {"pos": pos, "mat": np.broadcast_to(np.eye(3), (n, 2, 3, 3)).copy(),
             "qpos": np.asarray(angles, float)[:, None], "qvel": np.zeros((n, 0)), "contact": np.zeros((n, 0, 0), bool)}
    params = {"frame_c": np.broadcast_to([SCREW_C, [0.0, 0.0, 0.0]], (n, 2, 3)).copy(),
              "frame_h": np.broadcast_to([SCREW_H, [0.0075, 0.0075, 0.008]], (n, 2, 3)).copy(),
              "const_pos": np.zeros((n, 2, 3)), "init_center": np.zeros((n, 2, 3)),
              "press_rest": np.zeros((n, 0)), "press_far": np.zeros((n, 0))}
    lay = ProgramLayout(node, (), (), (), False, (), 0)
    return program_step(np, lay, state, params, init_memory(np, lay, n), 1)[1].success.tolist()


def test_a_seated_screw_turned_a_full_turn_is_tightened():
    turn = 2.0 * math.pi
    tips = [[0.0, 0.0, FLOOR], [0.0005, -0.0005, FLOOR + 0.002], [0.0, 0.0, FLOOR]]
    assert tightened(NODE, tips, [turn + 0.01, turn + 0.3, turn]) == [True, True, True]  # inclusive at one turn


def test_not_turned_enough_or_the_wrong_way_is_not_tightened():
    tips = [[0.0, 0.0, FLOOR]] * 3
    assert tightened(NODE, tips, [0.0, 0.9 * 2.0 * math.pi, -2.0 * math.pi]) == [False, False, False]
    loosening = dataclasses.replace(NODE, direction=-1.0)
    assert tightened(loosening, tips, [-2.0 * math.pi, 2.0 * math.pi, 0.0]) == [True, False, False]


def test_a_turned_socket_without_the_screw_in_it_is_not_tightened():
    turn = 2.0 * math.pi + 0.1
    tips = [[0.0, 0.0, SOCKET[2] + 0.008],  # resting on the rim, on the axis
            [0.0, 0.0, SOCKET[2] + 0.002],  # jammed in the upper half
            [0.03, 0.0, FLOOR],  # on the table beside the nut
            [0.0, 0.0, SOCKET[2] + 0.05]]  # held above it
    assert tightened(NODE, tips, [turn] * 4) == [False, False, False, False]


@pytest.fixture(scope="module")
def screw_plan():
    library = SpecLibrary.load([], strict=False)
    return compile_plan(library, library.get("task", "fasten_screws"), "standard", 0)


def test_tightened_compiles_to_each_nuts_thread_hinge_and_socket(screw_plan):
    model = screw_plan.model()
    program = compile_program(screw_plan)
    assert isinstance(program.layout.success, AllOf)
    nodes = program.layout.success.children
    assert all(isinstance(n, Tightened) for n in nodes)
    hinges = [int(model.joint(f"nut_{k}/thread").qposadr[0]) for k in "abc"]
    assert [program.index.qpos_adr[n.joint] for n in nodes] == hinges
    assert {n.direction for n in nodes} == {1.0} and {n.angle for n in nodes} == {2.0 * math.pi}
    assert all(abs(n.rest) < 0.01 for n in nodes)  # the thread at rest where the scene settled
    assert {program.index.frame_kind[n.socket] for n in nodes} == {1}  # the sockets' placement sites


@pytest.mark.parametrize("joint, message", [("nut_a/advance", "not the hinge of a thread"), ("nut_a/bolt", "thread")])
def test_tightened_names_a_thread_hinge(screw_plan, joint, message):
    plan = dataclasses.replace(screw_plan, program={"success": {"tightened": ["screw_a", joint, 1.0]}, "stages": []},
                               compiled_program={})
    with pytest.raises(ProgramError, match=message):
        compile_program(plan, screw_plan.model())


def test_the_thread_advances_by_its_pitch_and_gravity_does_not_unwind_it(screw_plan):
    model = screw_plan.model()
    data = screw_plan.initial_data(model)
    hinge, slide = model.joint("nut_a/thread"), model.joint("nut_a/advance")
    eq = next(e for e in range(model.neq) if model.eq_obj2id[e] == hinge.id)
    assert model.eq_type[eq] == mujoco.mjtEq.mjEQ_JOINT and model.eq_obj1id[eq] == slide.id
    assert model.eq_data[eq, 1] == pytest.approx(0.008 / (2.0 * math.pi))  # the asset's pitch, 8 mm a turn
    start = float(data.qpos[hinge.qposadr[0]])
    mujoco.mj_step(model, data, 500)  # one second at rest
    assert abs(float(data.qpos[hinge.qposadr[0]]) - start) < 0.01
    data.qfrc_applied[hinge.dofadr[0]] = 0.1  # N m, tightening: the socket turns and sinks
    mujoco.mj_step(model, data, 250)
    angle, sunk = float(data.qpos[hinge.qposadr[0]]), float(data.qpos[slide.qposadr[0]])
    assert angle > 1.0  # well past any play: the hinge turns freely beyond its frictionloss
    assert sunk == pytest.approx(angle * 0.008 / (2.0 * math.pi), abs=5e-4)
