"""Motion for the scripted experts: IK to world-frame gripper poses and joint trajectories with speed limits.

The experts plan in the world frame (object poses, annotation sites) and execute in the joint action mode, so
that what they send is exactly what a learned joint-space policy would send. `ArmPlanner` owns a scratch copy
of the simulation state and turns a world-frame goal for one arm into a list of per-control-step joint targets:
a straight Cartesian line (position lerp, orientation slerp) sampled at the gripper speed limit, each sample
solved by the backends' damped-least-squares IK seeded with the previous one (so the arm never flips branch
mid-move), then resampled so that no joint moves faster than its limit. Straight lines matter: a descent onto
an object or a transfer at a safe height must stay on the line, where a joint-space interpolation would sag.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np
from dojo.backends import actions as A
from dojo.backends.mujoco.kinematics import ArmKinematics, RobotIndex
from dojo.backends.rotations import mat_to_quat, quat_to_mat

ARM_INDEX = {"left": 0, "right": 1}
FAST = 0.40
"""Gripper speed for free-space moves (m/s)."""
CARRY = 0.25
"""Gripper speed while carrying: gentle accelerations keep a held object from swinging in the fingers."""
SLOW = 0.12
"""Gripper speed for the last centimetres before a contact (descend onto an object, lower onto a target)."""
TURN_RATE = 2.0
"""Gripper rotation speed (rad/s)."""
JOINT_SPEED = 2.0
"""Largest joint speed of a planned trajectory (rad/s): well inside what the servos track without lag."""
IK_ITERATIONS = 60
IK_TOLERANCE = 1e-5
MAX_STEPS = 250
"""Longest line (10 s at 25 Hz): a goal farther than any move in the workspace is a grounding error."""
LINE_TOLERANCE = 0.005
"""Largest TCP error along a Cartesian line before the move falls back to joint space (m)."""


@dataclass(frozen=True)
class Pose:
    """A world-frame gripper pose: TCP position [3] and rotation [3, 3] (columns: approach, finger axis, third)."""

    pos: np.ndarray
    rot: np.ndarray

    def shifted(self, offset: np.ndarray | list[float]) -> Pose:
        return Pose(self.pos + np.asarray(offset, dtype=float), self.rot)


class ArmPlanner:
    """Forward and inverse kinematics of both arms on a scratch MjData, in the world frame."""

    def __init__(self, model: mujoco.MjModel, robot: dict, control_hz: float) -> None:
        self.model = model
        self.index = RobotIndex.build(model, robot)
        self.kinematics = ArmKinematics(model, self.index)
        self.dt = 1.0 / control_hz
        self.lo, self.hi = self.index.limits.joint_lo, self.index.limits.joint_hi

    def sync(self, data: mujoco.MjData) -> None:
        """Take the simulation state (arm bases are fixed, but held objects do not matter to the IK)."""
        self.kinematics.sync(data)
        mujoco.mj_kinematics(self.model, self.kinematics.scratch)
        scratch = self.kinematics.scratch
        self.base_pos = scratch.xpos[self.index.bases].copy()
        self.base_rot = scratch.xmat[self.index.bases].reshape(2, 3, 3).copy()

    def fk(self, q: np.ndarray, arm: int) -> Pose:
        """World pose of `arm`'s TCP at arm joints q [2, J]."""
        pos, rot, _ = self.kinematics(q)
        return Pose(self.base_pos[arm] + self.base_rot[arm] @ pos[arm], self.base_rot[arm] @ rot[arm])

    def ik(self, q_seed: np.ndarray, arm: int, goal: Pose) -> tuple[np.ndarray, float]:
        """Joints [2, J] putting `arm`'s TCP at `goal` (the other arm unchanged) and the remaining position
        error in metres (large when the goal is out of reach: DLS then returns the closest pose it finds).

        Damped least squares in the world frame on one arm, with MuJoCo's own rotation routines: the same
        method as `backends.actions.solve_ik`, without its batching over both arms, since the expert solves
        thousands of single-arm goals per episode.
        """
        m, d, ix = self.model, self.kinematics.scratch, self.index
        adr, dof, site = ix.qpos_adr[arm], ix.dof_adr[arm], int(ix.ee_sites[arm])
        lo, hi = self.lo[arm], self.hi[arm]
        q = q_seed.copy()
        d.qpos[ix.qpos_adr] = q
        goal_quat, quat, err_quat, rotvec = np.empty(4), np.empty(4), np.empty(4), np.empty(3)
        mujoco.mju_mat2Quat(goal_quat, goal.rot.ravel())
        jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        damping = A.IK_DAMPING ** 2 * np.eye(6)
        for _ in range(IK_ITERATIONS):
            mujoco.mj_kinematics(m, d)
            pos_err = goal.pos - d.site_xpos[site]
            mujoco.mju_mat2Quat(quat, d.site_xmat[site])
            mujoco.mju_negQuat(err_quat, quat)
            mujoco.mju_mulQuat(err_quat, goal_quat, err_quat)
            mujoco.mju_quat2Vel(rotvec, err_quat, 1.0)
            err = np.concatenate([pos_err, A.IK_ROT_WEIGHT * rotvec])
            if np.max(np.abs(err)) < IK_TOLERANCE:
                break
            mujoco.mj_comPos(m, d)
            mujoco.mj_jacSite(m, d, jacp, jacr, site)
            jac = np.vstack([jacp[:, dof], A.IK_ROT_WEIGHT * jacr[:, dof]])
            dq = jac.T @ np.linalg.solve(jac @ jac.T + damping, err)
            dq *= min(1.0, A.IK_MAX_STEP / max(float(np.max(np.abs(dq))), 1e-12))
            q[arm] = np.clip(q[arm] + dq, lo, hi)
            d.qpos[adr] = q[arm]
        mujoco.mj_kinematics(m, d)
        return q, float(np.linalg.norm(goal.pos - d.site_xpos[site]))

    def line(self, q_start: np.ndarray, arm: int, goal: Pose, speed: float, seed: np.ndarray | None = None
             ) -> list[np.ndarray]:
        """Joint targets [2, J] per control step moving `arm`'s TCP on a straight line to `goal` at `speed`.

        When following the line drives the IK into a joint limit it cannot leave (the goal then ends up
        centimetres off), the move falls back to a joint-space interpolation to the best goal solution from
        `q_start` or `seed`: not straight, but it arrives.
        """
        start = self.fk(q_start, arm)
        distance = float(np.linalg.norm(goal.pos - start.pos))
        angle = _angle_between(start.rot, goal.rot)
        n = min(MAX_STEPS, max(1, math.ceil(max(distance / (speed * self.dt), angle / (TURN_RATE * self.dt)))))
        q0, q1 = mat_to_quat(np, start.rot), mat_to_quat(np, goal.rot)
        path, q, worst = [], q_start.copy(), 0.0
        for k in range(1, n + 1):
            s = _smooth(k / n)
            pose = Pose(start.pos + s * (goal.pos - start.pos), quat_to_mat(np, _slerp(q0, q1, s)))
            q, err = self.ik(q, arm, pose)
            worst = max(worst, err)
            path.append(q.copy())
        if worst > LINE_TOLERANCE and seed is not None:
            q_goal, err = self.ik(seed, arm, goal)
            if err < worst:
                path = [q_start + _smooth(k / n) * (q_goal - q_start) for k in range(1, n + 1)]
        return limit_joint_speed(q_start, path, JOINT_SPEED * self.dt)


def limit_joint_speed(q_start: np.ndarray, path: list[np.ndarray], max_step: float) -> list[np.ndarray]:
    """`path` with extra linear samples wherever a joint would move more than `max_step` in one step."""
    out, prev = [], q_start
    for q in path:
        n = max(1, math.ceil(float(np.max(np.abs(q - prev))) / max_step))
        out += [prev + (q - prev) * (k / n) for k in range(1, n + 1)]
        prev = q
    return out


def _smooth(s: float) -> float:
    """Smoothstep timing: zero speed at both ends, so moves start and stop without jerks."""
    return s * s * (3.0 - 2.0 * s)


def _slerp(a: np.ndarray, b: np.ndarray, s: float) -> np.ndarray:
    dot = float(np.dot(a, b))
    if dot < 0.0:
        b, dot = -b, -dot
    if dot > 0.9995:
        q = a + s * (b - a)
        return q / np.linalg.norm(q)
    theta = math.acos(dot)
    return (math.sin((1 - s) * theta) * a + math.sin(s * theta) * b) / math.sin(theta)


def _angle_between(a: np.ndarray, b: np.ndarray) -> float:
    cos = (np.trace(a.T @ b) - 1.0) / 2.0
    return math.acos(max(-1.0, min(1.0, cos)))
