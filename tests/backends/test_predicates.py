"""Every predicate of dojo/backends/predicates.py on hand-built states: each batch holds positive and negative rows."""

from __future__ import annotations

import math

import numpy as np
from dojo.backends import predicates as P
from dojo.backends.rotations import quat_to_mat


def rot_z(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


def rot_x(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[1.0, 0.0, 0.0], [0.0, math.cos(a), -math.sin(a)], [0.0, math.sin(a), math.cos(a)]])


def frames(poses: list[tuple], c=(0.0, 0.0, 0.0), h=(0.02, 0.02, 0.02)) -> tuple:
    """A batch of frames, one row per (pos, mat) pose, all with the same box."""
    n = len(poses)
    pos = np.array([p for p, _ in poses], dtype=float)
    mat = np.array([m for _, m in poses], dtype=float)
    return pos, mat, np.tile(np.asarray(c, float), (n, 1)), np.tile(np.asarray(h, float), (n, 1))


EYE = np.eye(3)
PLATE = ((0.0, 0.0, 0.76), EYE)  # a 16 x 16 x 2 cm slab centred at z 0.76: top at 0.77
PLATE_H = (0.08, 0.08, 0.01)


def test_on_needs_footprint_height_and_contact():
    cube = frames([((0.0, 0.0, 0.79), EYE),     # resting on top
                   ((0.05, -0.03, 0.79), EYE),  # off-centre, still over the plate
                   ((0.12, 0.0, 0.79), EYE),    # beside the plate
                   ((0.0, 0.0, 0.85), EYE),     # hovering 6 cm above
                   ((0.0, 0.0, 0.79), EYE)])    # on top but not touching (contact False below)
    plate = frames([PLATE] * 5, h=PLATE_H)
    touching = np.array([True, True, True, True, False])
    assert P.on(np, cube, plate, touching).tolist() == [True, True, False, False, False]


def test_on_uses_the_tilted_support_top_and_rejects_underneath():
    cube = frames([((0.0, 0.0, 0.79), EYE), ((0.0, 0.0, 0.73), EYE)])
    plate = frames([PLATE, PLATE], h=PLATE_H)
    assert P.supported(np, cube, plate).tolist() == [True, False]
    tilted = frames([((0.0, 0.0, 0.8), rot_x(45)), ((0.0, 0.0, 0.79), rot_x(45))])  # lowest point 0.8-0.028
    assert P.supported(np, tilted, plate).tolist() == [True, True]


def test_inside_box_and_region_extension():
    bin_box = frames([((0.2, 0.0, 0.78), rot_z(30))] * 3, h=(0.07, 0.07, 0.025))
    cube = frames([((0.2, 0.0, 0.775), EYE), ((0.2 + 0.09, 0.0, 0.775), EYE), ((0.2, 0.0, 0.9), EYE)])
    assert P.inside(np, cube, bin_box).tolist() == [True, False, False]
    region = frames([((0.0, 0.0, 0.75), EYE)] * 3, h=(0.1, 0.1, 0.0))
    cube = frames([((0.05, 0.0, 0.77), EYE), ((0.05, 0.0, 1.2), EYE), ((0.2, 0.0, 0.77), EYE)])
    assert P.inside(np, cube, region, up=P.REGION_HEIGHT).tolist() == [True, False, False]


def test_inside_uses_box_centre_offset():
    container = frames([((0.0, 0.0, 0.8), EYE)] * 2, h=(0.05, 0.05, 0.05))
    # the frame origin is 10 cm below the box centre: origin outside, box centre inside
    cube = frames([((0.0, 0.0, 0.72), EYE), ((0.0, 0.0, 0.62), EYE)], c=(0.0, 0.0, 0.1))
    assert P.inside(np, cube, container).tolist() == [True, False]


def test_upright():
    mats = np.stack([EYE, rot_x(10), rot_x(20), rot_x(180)])
    assert P.upright(np, mats).tolist() == [True, True, False, False]


def test_lifted_is_relative_to_the_initial_centre():
    pos, mat, c, _ = frames([((0.0, 0.0, 0.85), EYE), ((0.0, 0.0, 0.79), EYE)], c=(0.0, 0.0, 0.02))
    initial = np.array([[0.0, 0.0, 0.77], [0.0, 0.0, 0.77]])
    assert P.lifted(np, pos, mat, c, initial, 0.05).tolist() == [True, False]


def test_joint_bounds():
    q = np.array([0.1, 0.2, 0.3])
    assert P.joint_at_least(np, q, 0.2).tolist() == [False, True, True]
    assert P.joint_at_most(np, q, 0.2).tolist() == [True, True, False]


def test_aligned_position_and_yaw():
    target = frames([((0.0, 0.1, 0.75), EYE)] * 4)
    obj = frames([((0.01, 0.1, 0.80), rot_z(5)),    # 1 cm off, 5 cm higher (ignored), 5 degrees
                  ((0.03, 0.1, 0.75), EYE),         # 3 cm off
                  ((0.0, 0.1, 0.75), rot_z(15)),    # 15 degrees off
                  ((0.0, 0.1, 0.75), rot_z(358))])  # -2 degrees: wraps
    assert P.aligned(np, obj, target, 0.02, 10.0).tolist() == [True, False, False, True]


def test_near_3d_and_planar():
    a = frames([((0.0, 0.0, 0.8), EYE), ((0.0, 0.0, 0.9), EYE), ((0.1, 0.0, 0.8), EYE)])
    b = frames([((0.02, 0.0, 0.8), EYE)] * 3)
    assert P.near(np, a, b, 0.05, planar=False).tolist() == [True, False, False]
    assert P.near(np, a, b, 0.05, planar=True).tolist() == [True, True, False]


def test_contact_matrix_and_touched():
    geom_atom = np.array([3, 0, 0, 1, 2, 3])  # geom 0 untracked, 1-2 atom 0, 3 atom 1, 4 atom 2
    geom1 = np.array([[1, 0, 4], [2, 4, 0]])
    geom2 = np.array([[3, 5, 0], [4, 3, 0]])
    dist = np.array([[-0.001, -0.01, -0.01], [-0.001, 0.5, 0.0]])  # env 1's second contact is inactive
    m = P.contact_matrix(np, geom_atom, geom1, geom2, dist, 3)
    assert m.shape == (2, 3, 3) and (m == np.swapaxes(m, 1, 2)).all()
    assert P.touched(np, m, (0,), (1,)).tolist() == [True, False]
    assert P.touched(np, m, (1,), (2,)).tolist() == [False, False]
    assert P.touched(np, m, (0,), (1, 2)).tolist() == [True, True]


def test_press_hysteresis_and_counting():
    rest, far = np.zeros((1, 1)), np.full((1, 1), -0.01)
    down = np.zeros((1, 1), bool)
    count = np.zeros((1, 1), np.int32)
    # a jittering cap: down, half up (still down: hysteresis), fully up, down again
    for q in (-0.002, -0.008, -0.005, -0.008, -0.001, -0.009):
        now = P.press_down(np, np.full((1, 1), q), rest, far, down)
        count = P.count_presses(np, count, down, now)
        down = now
    assert int(count[0, 0]) == 2


def test_rotation_helpers_round_trip():
    from dojo.backends.rotations import mat_to_quat, quat_mul, rotation_error

    rng = np.random.default_rng(0)
    q = rng.normal(size=(16, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.sign(q[:, :1])
    m = quat_to_mat(np, q)
    assert np.allclose(mat_to_quat(np, m), q, atol=1e-9)
    assert np.allclose(quat_to_mat(np, quat_mul(np, q, q)), m @ m, atol=1e-9)
    err = rotation_error(np, np.broadcast_to(EYE, (1, 3, 3)), rot_z(170)[None])
    assert np.allclose(err, [[0.0, 0.0, math.radians(170)]], atol=1e-9)
