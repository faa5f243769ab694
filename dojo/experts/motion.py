"""Motion for the scripted experts: IK to world-frame gripper poses and joint trajectories with speed limits.

The experts plan in the world frame (object poses, annotation sites) and execute in the joint action mode, so
that what they send is exactly what a learned joint-space policy would send. `ArmPlanner` owns a scratch copy
of the simulation state and turns a world-frame goal for one arm into a list of per-control-step joint targets:
a straight Cartesian line (position lerp, orientation slerp) sampled at the gripper speed limit, each sample
solved by differential IK with `mink` (a QP per iteration: a frame task on the TCP, joint limits and a step limit
as hard constraints) seeded with the previous one (so the arm never flips branch mid-move), then resampled so
that no joint moves faster than its limit. Straight lines matter: a descent onto
an object or a transfer at a safe height must stay on the line, where a joint-space interpolation would sag.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mink
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
IK_STALL = 1e-6
"""An IK step smaller than this (rad) ends the iteration: the goal is out of reach from here."""
IK_SOLVER = "daqp"
"""The QP solver mink hands each IK step to (a dense active-set solver: six variables, a few dozen bounds)."""
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
        self.arms = [ArmIK(model, self.index, arm) for arm in range(2)]

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
        error in metres (large when the goal is out of reach: the IK then returns the closest pose it finds)."""
        q = q_seed.copy()
        q[arm], err = self.arms[arm].solve(q_seed[arm], goal)
        return q, err

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


class ArmIK:
    """Inverse kinematics of one arm with `mink`, on a model of that arm alone.

    The scene's model has every object's free joint (up to ~150 dofs with clutter); the IK only needs the arm's
    chain from its fixed base to the TCP site, so that chain is copied into a six-joint model (same body frames,
    joint axes and ranges) once per plan and mink solves on it. Each iteration is one mink QP: a frame task on
    the TCP (position cost 1, orientation weighted IK_ROT_WEIGHT, Levenberg-Marquardt damping IK_DAMPING^2, the
    same weighting as the backends' ee-mode IK), the joint limits and a per-iteration step bound IK_MAX_STEP as
    hard constraints, then integration of the step (dt = 1: the QP's velocity is the step).
    """

    def __init__(self, model: mujoco.MjModel, index: RobotIndex, arm: int) -> None:
        self.model = arm_chain_model(model, index, arm)
        self.configuration = mink.Configuration(self.model)
        self.task = mink.FrameTask("tcp", "site", position_cost=1.0, orientation_cost=A.IK_ROT_WEIGHT)
        self.lo, self.hi = self.model.jnt_range[:, 0].copy(), self.model.jnt_range[:, 1].copy()
        self.limits = [StepBox(self.lo, self.hi, A.IK_MAX_STEP)]
        self.site = self.model.site("tcp").id
        self.weights = np.array([1.0, 1.0, 1.0, A.IK_ROT_WEIGHT, A.IK_ROT_WEIGHT, A.IK_ROT_WEIGHT])

    def solve(self, q_seed: np.ndarray, goal: Pose) -> tuple[np.ndarray, float]:
        """Arm joints [J] for the TCP at `goal`, from `q_seed`, and the remaining position error (m)."""
        cfg, task = self.configuration, self.task
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, np.ascontiguousarray(goal.rot).ravel())
        task.set_target(mink.SE3(np.concatenate([quat, goal.pos])))
        cfg.update(np.clip(q_seed, self.lo, self.hi))
        for _ in range(IK_ITERATIONS):
            if np.max(np.abs(self.weights * task.compute_error(cfg))) < IK_TOLERANCE:
                break
            try:
                v = mink.solve_ik(cfg, [task], 1.0, IK_SOLVER, damping=A.IK_DAMPING ** 2, limits=self.limits)
            except mink.NoSolutionFound:
                break
            cfg.integrate_inplace(v, 1.0)
            if np.max(np.abs(v)) < IK_STALL:
                break  # at the closest pose it can reach (an unreachable goal, or a joint limit in the way)
        q = np.clip(cfg.q, self.lo, self.hi)
        return q, float(np.linalg.norm(goal.pos - cfg.data.site_xpos[self.site]))


class StepBox(mink.Limit):
    """The joint limits and a largest step per IK iteration as one box on the step: max(lo - q, -step) <= dq <=
    min(hi - q, step) (mink's ConfigurationLimit and VelocityLimit at dt = 1, in one constraint)."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, step: float) -> None:
        self.lo, self.hi, self.step = lo, hi, step
        n = len(lo)
        self.G = np.vstack([np.eye(n), -np.eye(n)])

    def compute_qp_inequalities(self, configuration: mink.Configuration, dt: float) -> mink.Constraint:
        q = configuration.q
        up = np.minimum(self.hi - q, self.step * dt)
        down = np.minimum(q - self.lo, self.step * dt)
        return mink.Constraint(G=self.G, h=np.concatenate([np.maximum(up, 0.0), np.maximum(down, 0.0)]))


def arm_chain_model(model: mujoco.MjModel, index: RobotIndex, arm: int) -> mujoco.MjModel:
    """A model of `arm` alone: its base where the scene has it, the links from the base to the TCP site with
    their hinge joints (in the order of the arm's joints), and the TCP site `tcp`. Kinematics only: the
    links get a nominal mass, no geoms."""
    site = int(index.ee_sites[arm])
    base = int(index.bases[arm])
    if model.body_parentid[base] != 0:
        raise ValueError("the arm base must be a child of the world body")
    chain, body = [], int(model.site_bodyid[site])
    while body != base:
        chain.append(body)
        body = int(model.body_parentid[body])
    spec = mujoco.MjSpec()
    spec.compiler.degree = False
    parent = spec.worldbody.add_body(name="base", pos=model.body_pos[base].tolist(),
                                     quat=model.body_quat[base].tolist())
    joints = []
    for body in reversed(chain):
        parent = parent.add_body(name=f"link{len(joints)}", pos=model.body_pos[body].tolist(),
                                 quat=model.body_quat[body].tolist(), mass=0.1, inertia=[1e-4, 1e-4, 1e-4])
        for j in range(model.body_jntadr[body], model.body_jntadr[body] + model.body_jntnum[body]):
            if model.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE:
                raise ValueError(f"arm joint {model.joint(j).name} is not a hinge")
            parent.add_joint(name=model.joint(j).name, type=mujoco.mjtJoint.mjJNT_HINGE,
                             axis=model.jnt_axis[j].tolist(), pos=model.jnt_pos[j].tolist(),
                             range=model.jnt_range[j].tolist(), limited=mujoco.mjtLimited.mjLIMITED_TRUE)
            joints.append(j)
    if list(model.jnt_qposadr[joints]) != list(index.qpos_adr[arm]):
        raise ValueError("the arm's chain joints are not its arm joints in order")
    parent.add_site(name="tcp", pos=model.site_pos[site].tolist(), quat=model.site_quat[site].tolist())
    return spec.compile()


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
