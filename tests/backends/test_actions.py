"""Action modes: layouts, clipping counts, non-finite rows, and the DLS IK on the robot's own kinematics."""

from __future__ import annotations

import math

import numpy as np
import pytest
from dojo.backends import actions as A
from dojo.backends.mujoco.kinematics import ArmKinematics, RobotIndex
from dojo.backends.rotations import mat_to_quat, quat_to_mat, rotation_error

LIMITS = A.ArmLimits(joint_lo=np.full((2, 6), -1.0), joint_hi=np.full((2, 6), 1.0), max_width=0.08, reach=1.0)


def test_action_dims():
    assert [A.action_dim(m) for m in A.ACTION_MODES] == [14, 16, 14, 16]
    with pytest.raises(ValueError, match="unknown action mode"):
        A.action_dim("torque")


def test_nonfinite_rows():
    a = np.zeros((3, 14))
    a[1, 4], a[2, 13] = np.nan, -np.inf
    assert A.nonfinite(np, a).tolist() == [False, True, True]


def test_joint_targets_clip_and_count():
    a = np.zeros((2, 14))
    a[0, 0], a[0, 6], a[0, 13] = 2.0, 1.5, -0.2   # joint over its limit, both grippers outside 0..1
    a[1, 7], a[1, 6], a[1, 13] = -0.5, 0.25, 1.0
    q, grip, clipped = A.joint_targets(np, a, np.zeros((2, 2, 6)), LIMITS, delta=False)
    assert clipped.tolist() == [3, 0]
    assert q[0, 0, 0] == 1.0 and q[1, 1, 0] == -0.5 and grip.tolist() == [[1.0, 0.0], [0.25, 1.0]]
    ctrl = A.to_ctrl(np, q, grip, LIMITS.max_width)
    assert ctrl.shape == (2, 14) and ctrl[1, 6] == pytest.approx(0.02) and ctrl[1, 7] == -0.5


def test_delta_joint_adds_to_the_measured_joints_and_zeroes_nonfinite_rows():
    q_now = np.full((2, 2, 6), 0.5)
    a = np.full((2, 14), 0.25)
    a[1, 3] = np.nan
    q, _, clipped = A.joint_targets(np, a, q_now, LIMITS, delta=True)
    assert np.allclose(q[0], 0.75) and clipped.tolist() == [0, 0]
    assert np.isfinite(q).all() and np.allclose(q[1], 0.5)  # the bad row is ignored (the backend ends it)


def test_ee_targets_clip_position_and_repair_zero_quaternions():
    a = np.zeros((2, 16))
    a[:, 3] = a[:, 11] = 1.0
    a[0, 0] = 1.7                       # beyond the reach box
    a[1, 8:15] = [0.3, 0.0, 0.2, 0.0, 0.0, 0.0, 0.0]  # zero quaternion on the right arm
    a[1, 15] = 2.0                      # gripper over 1
    quat_now = np.tile([math.cos(0.3), 0.0, 0.0, math.sin(0.3)], (2, 2, 1))
    pos, rot, grip, clipped = A.ee_targets(np, a, np.zeros((2, 2, 3)), quat_now, LIMITS, delta=False)
    assert clipped.tolist() == [1, 2] and pos[0, 0, 0] == 1.0 and grip[1, 1] == 1.0
    assert np.allclose(rot[1, 1], quat_to_mat(np, quat_now[1, 1]))  # degenerate -> keep orientation
    assert np.allclose(rot[0, 0], np.eye(3))


def test_delta_ee_composes_rotation_and_translation():
    a = np.zeros((1, 16))
    half = math.radians(10) / 2
    a[0, 0:7] = [0.01, 0.0, -0.02, math.cos(half), 0.0, 0.0, math.sin(half)]
    a[0, 8:15] = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    pos_now = np.array([[[0.3, 0.1, 0.2], [0.3, -0.1, 0.2]]])
    quat_now = np.tile([1.0, 0.0, 0.0, 0.0], (1, 2, 1))
    pos, rot, _, clipped = A.ee_targets(np, a, pos_now, quat_now, LIMITS, delta=True)
    assert np.allclose(pos[0, 0], [0.31, 0.1, 0.18]) and np.allclose(pos[0, 1], pos_now[0, 1])
    assert np.allclose(rotation_error(np, np.eye(3)[None], rot[:, 0]), [[0, 0, math.radians(10)]])
    assert clipped.tolist() == [0]


def test_ik_reaches_a_nearby_pose_on_the_robot(stack_plan):
    model = stack_plan.model()
    data = stack_plan.initial_data(model)
    index = RobotIndex.build(model, stack_plan.robot)
    fk = ArmKinematics(model, index)
    fk.sync(data)
    pos, rot = index.ee_pose(data)
    target_pos = pos + np.array([[0.05, 0.03, -0.04], [-0.03, 0.0, 0.05]])
    turn = quat_to_mat(np, np.array([math.cos(0.15), 0.0, math.sin(0.15), 0.0]))  # 17 degrees about y
    target_rot = rot @ turn
    q = A.solve_ik(np, fk, index.arm_q(data), target_pos, target_rot, index.limits.joint_lo, index.limits.joint_hi)
    reached_pos, reached_rot, _ = fk(q)
    assert np.abs(reached_pos - target_pos).max() < 2e-3
    assert np.linalg.norm(rotation_error(np, reached_rot, target_rot), axis=-1).max() < math.radians(1.0)
    assert (q >= index.limits.joint_lo).all() and (q <= index.limits.joint_hi).all()
    assert np.allclose(data.qpos, stack_plan.init_qpos)  # IK works on a scratch copy


def test_ik_on_an_unreachable_target_stays_finite_and_in_limits(stack_plan):
    model = stack_plan.model()
    data = stack_plan.initial_data(model)
    index = RobotIndex.build(model, stack_plan.robot)
    fk = ArmKinematics(model, index)
    fk.sync(data)
    target = np.tile([[2.0, 0.0, 0.5]], (2, 1))
    q = A.solve_ik(np, fk, index.arm_q(data), target, np.tile(np.eye(3), (2, 1, 1)), index.limits.joint_lo,
                   index.limits.joint_hi)
    assert np.isfinite(q).all()
    assert (q >= index.limits.joint_lo - 1e-12).all() and (q <= index.limits.joint_hi + 1e-12).all()


def test_mat_to_quat_matches_mujoco_on_ee_frames(stack_plan):
    data = stack_plan.initial_data()
    index = RobotIndex.build(stack_plan.model(), stack_plan.robot)
    _, rot = index.ee_pose(data)
    assert np.allclose(mat_to_quat(np, rot), index.ee_quat(rot))


def test_action_maths_trace_under_jax_jit():
    """The MJX backend's path: ee targets and IK with jax.numpy under one jit, against a linear toy FK."""
    jax = pytest.importorskip("jax")
    jnp = jax.numpy
    jac = np.random.default_rng(2).normal(size=(2, 6, 6))
    jac[:, 3:] = 0.0  # position only, so the linear FK below is exact

    def fk(q):
        return jnp.einsum("mij,mj->mi", jnp.asarray(jac[:, :3]), q), jnp.tile(jnp.eye(3), (2, 1, 1)), jnp.asarray(jac)

    def solve(action):
        pos, rot, grip, clipped = A.ee_targets(jnp, action, jnp.zeros((1, 2, 3)),
                                               jnp.tile(jnp.asarray([1.0, 0.0, 0.0, 0.0]), (1, 2, 1)), LIMITS, False)
        q = A.solve_ik(jnp, fk, jnp.zeros((2, 6)), pos[0], rot[0], -3.0, 3.0, iterations=10)
        return q, A.to_ctrl(jnp, q[None], grip, LIMITS.max_width), clipped

    action = np.zeros((1, 16))
    action[0, :8] = [0.1, 0.0, 0.05, 1.0, 0.0, 0.0, 0.0, 0.5]
    action[0, 8:] = [0.0, -0.1, 0.02, 1.0, 0.0, 0.0, 0.0, 3.0]
    q, ctrl, clipped = jax.jit(solve)(jnp.asarray(action))
    reached = np.einsum("mij,mj->mi", jac[:, :3], np.asarray(q))
    assert np.abs(reached - [[0.1, 0.0, 0.05], [0.0, -0.1, 0.02]]).max() < 1e-4
    assert np.asarray(clipped).tolist() == [1] and ctrl.shape == (1, 14)
