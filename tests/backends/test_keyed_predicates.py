"""Keyed insertion's predicate words on hand-built states (positive and negative): plugged(plug, socket) with its
position and heading tolerances, turned(object/joint, angle); and both compiled against insert_key, whose
tolerances no setting loosens."""

from __future__ import annotations

import math

import numpy as np
import pytest
from dojo.backends.predicate_program import ProgramLayout, compile_program, init_memory, program_step
from dojo.compiler.plan import compile_plan
from dojo.compiler.spec_library import SpecLibrary
from dojo.language.predicates.plugged import Plugged
from dojo.language.predicates.turned import Turned

SOCKET_HALF = [0.002, 0.006, 0.01375]
"""A keyway 4 x 12 mm, 27.5 mm deep: the socket frame is the box's centre, its floor 13.75 mm below."""
SOCKET_AT = [0.1, 0.2, 0.8]
FLOOR = [0.1, 0.2, 0.8 - 0.01375]
KEY = Plugged(plug=0, socket=1, pos_tol=0.002, yaw_tol=math.radians(8))


def yaw_mat(degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def step(node, pos=None, mats=None, qpos=None) -> list[bool]:
    """The node's value on N environments: pos [N][F][3] frame positions, mats [N][F] yaws in degrees (frame 1 is
    the socket box, frame 0 a point), qpos [N][J]."""
    n = len(pos if pos is not None else qpos)
    f = len(pos[0]) if pos is not None else 0
    pos = np.zeros((n, 0, 3)) if pos is None else np.asarray(pos, float)
    mats = np.zeros((n, 0, 3, 3)) if mats is None else np.array([[yaw_mat(y) for y in row] for row in mats])
    state = {"pos": pos, "mat": mats,
             "qpos": np.asarray(qpos if qpos is not None else np.zeros((n, 0)), float),
             "qvel": np.zeros((n, 0)), "contact": np.zeros((n, 0, 0), bool)}
    half = np.zeros((n, f, 3))
    if f:
        half[:, 1] = SOCKET_HALF
    params = {"frame_c": np.zeros((n, f, 3)), "frame_h": half, "const_pos": np.zeros((n, f, 3)),
              "init_center": np.zeros((n, f, 3)), "press_rest": np.zeros((n, 0)), "press_far": np.zeros((n, 0))}
    lay = ProgramLayout(node, (), (), (), False, (), 0)
    return program_step(np, lay, state, params, init_memory(np, lay, n), 1)[1].success.tolist()


def plugged(tips: list[list[float]], yaws: list[float], socket_yaw: float = 0.0) -> list[bool]:
    return step(KEY, [[tip, SOCKET_AT] for tip in tips], [[y, socket_yaw] for y in yaws])


def off(dx: float = 0.0, dy: float = 0.0, dz: float = 0.0) -> list[float]:
    return [FLOOR[0] + dx, FLOOR[1] + dy, FLOOR[2] + dz]


def test_a_tip_on_the_socket_floor_is_plugged_within_pos_tol():
    assert plugged([off(), off(dx=0.0015), off(dy=-0.0019, dz=0.0005)], [0, 0, 0]) == [True, True, True]


def test_a_tip_off_by_3_mm_or_resting_at_the_entrance_is_not_plugged():
    # pushed in beside the slot, or standing on the socket's face with the whole depth still to go
    assert plugged([off(dx=0.003), off(dy=0.0021), off(dz=0.0275)], [0, 0, 0]) == [False, False, False]


def test_pos_tol_is_inclusive_and_measured_in_3d():
    d = 0.002 / math.sqrt(3.0) * 0.999
    assert plugged([off(d, d, d), off(0.0015, 0.0, 0.0015)], [0, 0]) == [True, False]


def test_the_heading_must_match_within_yaw_tol_as_an_axis():
    # a symmetric key turned half round fits the same keyway; a quarter turn or 12 degrees does not
    assert plugged([off()] * 6, [7.9, -7.9, 180.0, 175.0, 90.0, 12.0]) == [True, True, True, True, False, False]


def test_plugged_follows_a_turned_socket():
    # the keyway turned 60 degrees with its cylinder: a key turned with it is still plugged, one left behind is not
    assert plugged([off(), off()], [60.0, 0.0], socket_yaw=60.0) == [True, False]


LOCK = Turned(joint=0, start=0.0, angle=math.radians(80))


def test_turned_needs_the_angle_either_way():
    q = [[math.radians(80)], [math.radians(-85)], [math.radians(79)], [0.0]]
    assert step(LOCK, qpos=q) == [True, True, False, False]


def test_turned_counts_from_the_start_position():
    node = Turned(joint=1, start=0.5, angle=math.radians(80))
    q = [[0.0, 0.5 + math.radians(81)], [0.0, math.radians(81)]]
    assert step(node, qpos=q) == [True, False]


@pytest.fixture(scope="module")
def library():
    return SpecLibrary.load([], strict=False)


def test_insert_key_compiles_to_the_keyway_and_the_cylinder(library):
    plan = compile_plan(library, library.get("task", "insert_key"), "standard", 0)
    program = compile_program(plan)
    seated, turned = program.layout.success.children
    assert (seated.pos_tol, round(math.degrees(seated.yaw_tol), 9)) == (0.002, 8.0)
    model = plan.model()
    assert program.index.qpos_adr[turned.joint] == int(model.joint("lock/plug").qposadr[0])
    assert turned.start == 0.0 and turned.angle == pytest.approx(math.radians(80))
    assert "events" in plan.requires  # the lock and unlock: mjx does not run them, so dojo run routes to mujoco


def test_no_setting_loosens_the_tolerances(library):
    """The Generalization random setting redraws looks, instances and clutter, never a task's tolerances."""
    task = library.get("task", "insert_key")
    nodes = [compile_program(compile_plan(library, task, setting, 1)).layout.success.children[0]
             for setting in ("standard", "random")]
    assert {(n.pos_tol, n.yaw_tol) for n in nodes} == {(0.002, math.radians(8))}
