"""The scripted experts' `open` and `close` skills: articulated fixtures (drawers, doors, lids) moved by a handle.

Nothing here is written per asset. Everything comes from the compiled model and the asset's annotations:

- the *interaction point* is an annotation on the moving link (the step's `target`, e.g. `cabinet/handle`, or by
  default the one that leads the motion: foremost along a slide's opening direction, farthest from a hinge's
  axis, where the least force moves it and where handles and free edges are);
- the *joint* is the one that moves that link; its world axis and anchor are read from the simulator state, its
  range from the model, and its *closed end* is the end of the range nearest the position it started in (every
  articulated asset starts closed);
- the *grasp* pinches the point's annotation box across its thinnest side, the gripper approaching along the
  direction the point moves when closing (into a drawer's front, a door's face), so that the pull that opens is
  along the fingers and the pinch is where a hand grips a handle;
- the *motion* keeps that grasp rigid on the link: the TCP pose for joint value q is the grasp pose moved by the
  joint's own transform (a translation along a slide's axis, a rotation about a hinge's axis), sampled at the
  gripper speed and solved by the same IK as every other move, so a drawer is pulled straight and a door handle
  swept along its arc.

`close` is `open` towards the closed end. A motion the arm cannot follow to its end (a door swung through a right
angle turns the wrist past its limits) is done as far as it reaches, then grasped again from where the joint is;
so is a move that ended short (the pinch slipped).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from dojo.experts.motion import FAST, JOINT_SPEED, SLOW, Pose, limit_joint_speed
from dojo.experts.skills import (
    APPROACH,
    FINGERTIP,
    GRIP_STEPS,
    REACH_TOL,
    SkillContext,
    SkillFailed,
    SkillGen,
    free_other_arm,
    open_and_retreat,
)

TILTS = (0.0, 0.3, -0.3, 0.6, -0.6)
"""Turns of the approach about the finger axis tried in turn when the straight-on grasp is out of reach (rad)."""
TIP_GAP = 0.004
"""How far short of the surface behind the handle (a drawer's front, a door's face) the fingertips stop (m)."""
DRIVE_SPEED = 0.08
"""TCP speed while moving a fixture: slower than SLOW, a pinch holds better against a slow pull (m/s)."""
BACKOFFS = (APPROACH, 0.05, 0.035)
"""Pre-grasp distances back along the approach tried in turn (m); the last still clears a 3 cm handle."""
PATH_SAMPLES = 8
"""Poses along a planned joint motion checked for reach before an arm and grasp are chosen."""
PATH_TOL = 0.01
"""Largest IK error along a motion the arm is taken to follow (m): the pinch absorbs a few millimetres."""
GOAL_TOL = 0.1
"""Fraction of the joint's range a move may end short of its goal before it is resumed."""
CLOSE_PAST = 0.03
"""`close` aims this fraction of the range past the closed end, so that the joint reaches its limit."""
REGRASPS = 4
"""Grasps a move may take: a wide swing is done in parts, and a slipped pinch is taken up again."""


@dataclass(frozen=True)
class Articulation:
    """One joint of an object and the point that drives it: world anchor and unit axis, range, closed end."""

    joint: int
    qpos_adr: int
    hinge: bool
    anchor: np.ndarray
    axis: np.ndarray
    lo: float
    hi: float
    closed: float
    point: str

    @property
    def open_end(self) -> float:
        return self.hi if self.closed == self.lo else self.lo

    def goal(self, amount: float) -> float:
        """Joint value `amount` of the way from the closed end to the open end."""
        return self.closed + amount * (self.open_end - self.closed)

    def moved(self, pose: Pose, dq: float) -> Pose:
        """`pose` carried rigidly with the link as the joint moves by dq."""
        if not self.hinge:
            return Pose(pose.pos + dq * self.axis, pose.rot)
        turn = _axis_angle(self.axis, dq)
        return Pose(self.anchor + turn @ (pose.pos - self.anchor), turn @ pose.rot)

    def tangent(self, point: np.ndarray) -> np.ndarray:
        """Unit direction in which `point` on the link moves as the joint opens."""
        sign = 1.0 if self.open_end > self.closed else -1.0
        v = np.cross(self.axis, point - self.anchor) if self.hinge else self.axis
        return sign * v / max(float(np.linalg.norm(v)), 1e-9)


def articulation(ctx: SkillContext, obj: str, target: str | None) -> Articulation:
    """The joint of `obj` that `target` (an annotation of it, or the default interaction point) rides on."""
    model, plan = ctx.model, ctx.plan
    joints = {model.joint(j).id: j for j in plan.objects[obj]["joints"]}
    if not joints:
        raise SkillFailed(f"{obj} has no joint to open or close")

    def joint_of(site: str) -> int | None:
        body = int(model.site_bodyid[model.site(site).id])
        while body > 0:
            for j in range(model.body_jntadr[body], model.body_jntadr[body] + model.body_jntnum[body]):
                if j in joints:
                    return j
            body = int(model.body_parentid[body])
        return None

    sites = plan.objects[obj]["sites"]
    if target is not None:
        point = target.split("/", 1)[1] if "/" in target else target
        if point not in sites or joint_of(sites[point]) is None:
            raise SkillFailed(f"{obj}/{point} is not an annotation on a moving part of {obj}")
        return _articulation(ctx, joint_of(sites[point]), point)
    moving = {name: joint_of(site) for name, site in sites.items()}
    candidates = [_articulation(ctx, j, name) for name, j in moving.items() if j is not None]
    if not candidates:
        raise SkillFailed(f"{obj} has no annotation on a moving part to grasp")
    return max(candidates, key=lambda a: _lead(ctx, obj, a))


def _articulation(ctx: SkillContext, joint: int, point: str) -> Articulation:
    """The joint as it stands now (a free-standing box's hinge moves with the box), its closed end the range end
    nearest where the plan started it."""
    model, data = ctx.model, ctx.data
    adr = int(model.jnt_qposadr[joint])
    lo, hi = (float(v) for v in model.jnt_range[joint])
    start = float(ctx.plan.init_qpos[adr])
    closed = lo if abs(start - lo) <= abs(start - hi) else hi
    hinge = bool(model.jnt_type[joint] == mujoco.mjtJoint.mjJNT_HINGE)
    return Articulation(joint, adr, hinge, data.xanchor[joint].copy(), data.xaxis[joint].copy(), lo, hi, closed, point)


def _lead(ctx: SkillContext, obj: str, art: Articulation) -> float:
    """How well an annotation leads its joint's motion: a hinge's lever arm, a slide's reach along its opening."""
    p = ctx.scene.site(obj, art.point).center
    if art.hinge:
        r = p - art.anchor
        return float(np.linalg.norm(r - np.dot(r, art.axis) * art.axis))
    return float(np.dot(p - art.anchor, art.tangent(p)))


def joint_value(ctx: SkillContext, art: Articulation) -> float:
    """The joint's position in the simulator state the expert last observed."""
    return float(ctx.data.qpos[art.qpos_adr])


# ---- grasping the interaction point ----

@dataclass(frozen=True)
class Grasp:
    """A pinch of the interaction point: the arm, its TCP pose, the gripper opening, how far back along the
    approach the pre-grasp pose is (m), and the fraction of the planned motion the arm follows from it."""

    arm: int
    pose: Pose
    opening: float
    backoff: float
    reach: float

    @property
    def pre(self) -> Pose:
        return self.pose.shifted(-self.backoff * self.pose.rot[:, 0])


def handle_grasp(ctx: SkillContext, arm: str, obj: str, art: Articulation, dq: float) -> Grasp:
    """The pinch of the interaction point that follows the motion by dq farthest: the approach along the point's
    closing direction, fingers across its thinnest side, the approach turned about the finger axis (TILTS) or
    the wrist turned half round (a wrist cannot follow a door through a right angle: the rest is done after
    grasping again)."""
    site = ctx.scene.site(obj, art.point)
    half = np.maximum(site.half, 1e-3)
    approach = -art.tangent(site.center)
    axes = []
    for k in range(3):
        f = site.rot[:, k] - np.dot(site.rot[:, k], approach) * approach
        if np.linalg.norm(f) > 0.5:
            axes.append((2.0 * half[k], f / np.linalg.norm(f)))
    width, finger = min(axes, key=lambda w: w[0])
    if width > ctx.max_width - 0.012:
        raise SkillFailed(f"{obj}/{art.point} is wider than the gripper opens")
    depth = float(np.abs(site.rot.T @ approach) @ half)  # how far the handle stands out along the approach
    tips = site.center + (depth - TIP_GAP) * approach
    opening = min(1.0, (width + 0.03) / ctx.max_width)
    arms = [0, 1] if arm == "auto" else [ctx.choose_arm(arm, site.center)]
    best: tuple[tuple[float, float], Grasp] | None = None
    for tilt in TILTS:
        for sign in (1.0, -1.0):
            a = _axis_angle(sign * finger, tilt) @ approach
            pose = Pose(tips - FINGERTIP * a, np.column_stack([a, sign * finger, np.cross(a, sign * finger)]))
            for k in arms:
                backoff, reach, err = _path_reach(ctx, k, art, pose, dq)
                if best is None or (reach, -err) > best[0]:
                    best = ((reach, -err), Grasp(k, pose, opening, backoff, reach))
        if best is not None and best[1].reach == 1.0 and -best[0][1] < REACH_TOL:
            break
    assert best is not None
    if best[1].reach <= 0.0:
        raise SkillFailed(f"no arm reaches {obj}/{art.point} and moves it")
    return best[1]


def _path_reach(ctx: SkillContext, arm: int, art: Articulation, grasp: Pose, dq: float
                ) -> tuple[float, float, float]:
    """The pre-grasp back-off (the longest of BACKOFFS the arm reaches: a handle swung close to the arm's base
    leaves little room), how much of the motion by dq (a fraction) the arm then follows within PATH_TOL, and
    its worst IK error up to there: each pose solved from the previous one, as the executed motion will be.
    Reach 0 when the grasp itself is out of reach."""
    for backoff in BACKOFFS:
        q, worst = ctx.planner.ik(ctx._seed(arm, grasp.pos), arm, grasp.shifted(-backoff * grasp.rot[:, 0]))
        if worst <= PATH_TOL:
            break
    reach = 0.0
    for k in range(PATH_SAMPLES + 1):
        q, err = ctx.planner.ik(q, arm, art.moved(grasp, dq * k / PATH_SAMPLES))
        if max(worst, err) > PATH_TOL:
            break
        worst, reach = max(worst, err), k / PATH_SAMPLES
    return backoff, reach, worst


# ---- moving the joint ----

def drive(ctx: SkillContext, arm: int, art: Articulation, grasp: Pose, dq: float) -> np.ndarray:
    """Action rows moving the grasp rigidly with the link by dq: straight for a slide, along the arc for a hinge,
    smoothly started and stopped, at DRIVE_SPEED or slower (JOINT_SPEED)."""
    radius = float(np.linalg.norm(np.cross(art.axis, grasp.pos - art.anchor))) if art.hinge else 1.0
    n = max(2, math.ceil(abs(dq) * radius / (DRIVE_SPEED * ctx.planner.dt)))
    path, q = [], ctx.q.copy()
    for k in range(1, n + 1):
        s = k / n
        q, _ = ctx.planner.ik(q, arm, art.moved(grasp, dq * s * s * (3.0 - 2.0 * s)))
        path.append(q.copy())
    path = limit_joint_speed(ctx.q, path, JOINT_SPEED * ctx.planner.dt)
    return ctx.rows(path + [path[-1]] * 6)


def move_joint(ctx: SkillContext, arm: str, obj: str, target: str | None, amount: float | None) -> SkillGen:
    """Drive the joint to `amount` of its range from the closed end (`None`: closed, aiming slightly past the
    end): grasp the interaction point, move it as far along the motion as the arm follows, let go and back off
    along the approach; grasp again from where it is until the joint is there (REGRASPS in all)."""
    art = articulation(ctx, obj, target)
    goal = art.goal(-CLOSE_PAST if amount is None else amount)
    end = min(max(goal, art.lo), art.hi)
    tol = GOAL_TOL * (art.hi - art.lo)
    for _ in range(REGRASPS):
        art = _articulation(ctx, art.joint, art.point)  # the axis as the object stands now (a free box may move)
        if abs(joint_value(ctx, art) - end) < tol:
            return
        grasp = handle_grasp(ctx, arm, obj, art, goal - joint_value(ctx, art))
        a = grasp.arm
        yield from free_other_arm(ctx, a)
        yield ctx.gripper(a, grasp.opening, 1)
        yield ctx.line(a, grasp.pre, FAST)
        yield ctx.line(a, grasp.pose, SLOW)
        yield ctx.gripper(a, 0.0, GRIP_STEPS)
        yield drive(ctx, a, art, grasp.pose, grasp.reach * (goal - joint_value(ctx, art)))
        yield from open_and_retreat(ctx, a)
    if abs(joint_value(ctx, art) - end) >= tol:
        raise SkillFailed(f"{obj}: joint {ctx.model.joint(art.joint).name} at {joint_value(ctx, art):.3f}, "
                          f"not {end:.3f}")


def open_joint(ctx: SkillContext, arm: str, obj: str, target: str | None = None, amount: float = 1.0) -> SkillGen:
    """`open`: the joint to `amount` (a fraction of its range) from its closed end."""
    return move_joint(ctx, arm, obj, target, amount)


def close_joint(ctx: SkillContext, arm: str, obj: str, target: str | None = None) -> SkillGen:
    """`close`: the joint back to its closed end."""
    return move_joint(ctx, arm, obj, target, None)


def run_open(ctx: SkillContext, step: dict) -> SkillGen:
    """The `open` skill word's runner."""
    return open_joint(ctx, step.get("arm", "auto"), step.get("object"), step.get("target"),
                      float(step.get("amount", 1.0)))


def run_close(ctx: SkillContext, step: dict) -> SkillGen:
    """The `close` skill word's runner."""
    return close_joint(ctx, step.get("arm", "auto"), step.get("object"), step.get("target"))


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix of `angle` about the unit `axis` (Rodrigues)."""
    x, y, z = axis / max(float(np.linalg.norm(axis)), 1e-12)
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)
