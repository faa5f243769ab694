"""Skills of the Precision tasks that the pick-and-place library has no word for: `strike` (a tool's head hits a
target at a set speed: a mallet on a xylophone bar) and `pour` (a container's contents tipped into another).

Each is a generator of joint-mode segments like the skills of `dojo.experts.skills`, built from the same
primitives (grasp, straight TCP lines, measured corrections), and resumed only when the previous segment has
run, so each move starts from where the held tool really is.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from dojo.experts.motion import CARRY, FAST, SLOW, Pose
from dojo.experts.skills import (
    CLEARANCE,
    SkillContext,
    SkillFailed,
    SkillGen,
    carry_to,
    free_other_arm,
    grasp,
)

STRIKE_SPEED = 0.25
"""Commanded TCP speed (m/s) of the downward stroke. The arm lags its command, so the head meets the target at
about half this, still twice the 5 cm/s a task's `struck` asks for, and slow enough that a sprung bar's 8 mm of
travel lasts longer than one 40 ms control step (the predicates sample the state once per step)."""
STRIKE_LIFT = 0.03
"""Height (m) of the tool's striking face above the target before each stroke."""
STRIKE_DEPTH = 0.016
"""How far (m) the stroke is aimed past the target's rest surface: well past the travel of a sprung bar, so the
head still moves at full speed when it meets the bar (a stroke slows down only near its end)."""
STRIKE_TILT = 0.3
"""Roll (rad) of the gripper about its finger axis that dips a held tool's head below the fingertips: a mallet
grasped off the table hangs with the fingertips level with its head, and they would land on the next bar."""
AIM_TOL = 0.002
"""A head found farther than this (m) from its aim above the target is moved once more before the stroke."""


POUR_ABOVE = 0.045
"""Height (m) of the held container's mouth above the target's mouth while it pours."""
POUR_ANGLE = 2.2
"""How far (rad) the container is tipped about the fingers' axis to empty it (120 degrees: past the horizontal,
so that round contents roll out over a tapered cup's rim)."""
POUR_LEAN = 1.3
"""How far (rad) the container is leant while it is lowered to and raised from its pouring height: short of the
angle at which round contents roll out, so nothing falls on the way."""
POUR_DESCENT = 0.04
"""The leant container travels this much (m) above its pouring height and comes down onto it vertically, so it
does not sweep the target's rim on the way."""
POUR_STEPS = 40
POUR_TRIES = 2
"""Tips in all: one more when something is still inside after the first (a ball caught behind the fingers)."""
TIP_STEPS = 6
"""Poses the tip from POUR_LEAN to POUR_ANGLE goes through (each with the mouth at its aim)."""
"""Control steps the container is held tipped while its contents run out."""


def held_arm(ctx: SkillContext, obj: str, arm: str) -> SkillGen:
    """The arm holding `obj`, grasping it first (with `arm`, or the nearer one) when no arm holds it; the
    generator's return value is the arm index."""
    a = next((k for k, held in ctx.held.items() if held == obj), None)
    if a is None:
        a = ctx.choose_arm(arm, ctx.scene.box(obj).center)
        yield from free_other_arm(ctx, a)
        yield from grasp(ctx, a, obj)
    return a


def strike(ctx: SkillContext, arm: str, tool: str, target: str, speed: float = STRIKE_SPEED) -> SkillGen:
    """Hit `target` (an `object/annotation` point on the surface to strike) with the `head` of the held `tool`:
    the head is brought above the point, the gripper keeping the attitude it grasped with, measured and
    corrected there, driven down through the point at `speed`, and lifted again."""
    if "/" not in target:
        raise SkillFailed(f"strike: target {target!r} is not an object/annotation point")
    a = yield from held_arm(ctx, tool, arm)
    if not ctx.scene.has_site(tool, "head"):
        raise SkillFailed(f"strike: {tool} has no `head` annotation to strike with")
    point = ctx.scene.site(*target.split("/", 1)).center
    head = ctx.scene.site(tool, "head").center
    here = ctx.tcp(a)
    key = ("strike", a, tool)
    if key not in ctx.memo:
        # the head's lowest point under its centre while the tool lies level in the fingers, then the roll that
        # dips the head (kept for the following strikes: the tool stays in this attitude)
        ctx.memo[key] = (float(head[2] - ctx.scene.box(tool).bottom), _dip(here, head - ctx.actual_tcp(a)))
    below, rot = ctx.memo[key]
    if not np.allclose(rot, here.rot):
        yield ctx.line(a, Pose(here.pos, rot), CARRY / 2, settle=6)
        here, head = ctx.tcp(a), ctx.scene.site(tool, "head").center
    aim = point + [0.0, 0.0, below + STRIKE_LIFT]
    pose = Pose(here.pos + aim - head, rot)
    yield ctx.line(a, Pose(np.array([*pose.pos[:2], max(pose.pos[2], here.pos[2])]), rot), CARRY, settle=0)
    yield ctx.line(a, pose, CARRY, settle=6)
    error = aim - ctx.scene.site(tool, "head").center
    if float(np.linalg.norm(error)) > AIM_TOL:
        pose = pose.shifted(error)
        yield ctx.line(a, pose, CARRY / 2, settle=6)
    yield ctx.line(a, pose.shifted([0.0, 0.0, -(STRIKE_LIFT + STRIKE_DEPTH)]), speed, settle=8)
    yield ctx.line(a, pose, FAST, settle=2)


def pour(ctx: SkillContext, arm: str, obj: str, target: str) -> SkillGen:
    """Empty the container `obj` into `target`. Grasp it unless held (a container gripped by its rim turns about
    the fingers' axis near the middle of its mouth), lift it clear of the table, lean it short of spilling (a
    leant cup passes over a tall target that an upright one, hanging under the gripper, would hit), bring its
    mouth (`top` frame) POUR_ABOVE the target's (`opening`, else `top`), tip it by POUR_ANGLE with the mouth
    held there and hold while the contents run out; then the same way back, and put it down where it stood.
    Leaning and tipping go the way the arm reaches best at the target."""
    start = ctx.scene.box(obj).center.copy()
    a = yield from held_arm(ctx, obj, arm)
    goal = ctx.scene.site(target, "opening" if ctx.scene.has_site(target, "opening") else "top").center
    here = ctx.tcp(a)
    box = ctx.scene.box(obj)
    local = ctx.actual_tcp_rot(a).T @ (ctx.scene.site(obj, "top").center - ctx.actual_tcp(a))  # mouth, in the hand
    aim = goal + [0.0, 0.0, POUR_ABOVE]
    turns = _tip_poses(ctx, a, here.rot, local, aim)
    leaning, tipped = turns[0], turns[-1]
    up = Pose(np.array([*here.pos[:2], max(ctx.scene.table_z + float(here.pos[2] - box.bottom) + CLEARANCE,
                                               here.pos[2])]), here.rot)
    travel = max(leaning.pos[2], up.pos[2]) + POUR_DESCENT
    yield ctx.line(a, up, CARRY, settle=0)
    yield ctx.line(a, Pose(up.pos, leaning.rot), SLOW, settle=4)
    yield ctx.line(a, Pose(np.array([*up.pos[:2], travel]), leaning.rot), CARRY, settle=0)
    yield ctx.line(a, Pose(np.array([*leaning.pos[:2], travel]), leaning.rot), CARRY, settle=0)
    yield ctx.line(a, leaning, SLOW, settle=6)
    error = aim - ctx.scene.site(obj, "top").center
    if float(np.linalg.norm(error)) > AIM_TOL:
        turns = [t.shifted(error) for t in turns]
        leaning = turns[0]
        yield ctx.line(a, leaning, SLOW, settle=4)
    for _ in range(POUR_TRIES):  # tipped again while anything is left inside
        for turn in turns[1:]:  # through the poses between: the mouth stays put while the cup turns about it
            yield ctx.line(a, turn, SLOW, settle=0)
        yield ctx.hold(POUR_STEPS)
        for turn in turns[-2::-1]:
            yield ctx.line(a, turn, SLOW, settle=0)
        if not _contents(ctx, obj):
            break
    yield ctx.line(a, Pose(np.array([*leaning.pos[:2], travel]), leaning.rot), SLOW, settle=0)
    yield ctx.line(a, Pose(np.array([*up.pos[:2], travel]), leaning.rot), CARRY, settle=0)
    yield ctx.line(a, Pose(up.pos, leaning.rot), CARRY, settle=0)
    yield ctx.line(a, up, SLOW, settle=2)
    yield from carry_to(ctx, a, obj, start + [0.0, 0.0, 0.004])


def _contents(ctx: SkillContext, container: str) -> list[str]:
    """The objects whose centre is within the container's `inside` box (what is still to pour)."""
    box = ctx.scene.site(container, "inside")
    return [name for name in ctx.scene.others((container,))
            if np.all(np.abs(box.rot.T @ (ctx.scene.box(name).center - box.center)) <= box.half + 0.005)]


def _tip_poses(ctx: SkillContext, arm: int, rot: np.ndarray, mouth: np.ndarray, aim: np.ndarray) -> list[Pose]:
    """The gripper poses that hold a container's mouth (`mouth`, in the gripper's frame) at `aim`, the gripper
    turned from `rot` about its finger axis from POUR_LEAN to POUR_ANGLE in TIP_STEPS steps: in the sense (either
    way round) that the arm reaches with the smaller IK error at both ends."""
    axis = rot[:, 1] / np.linalg.norm(rot[:, 1])
    best = None
    for sense in (1.0, -1.0):
        poses = []
        for angle in np.linspace(POUR_LEAN, POUR_ANGLE, TIP_STEPS + 1):
            turned = _axis_angle(axis, sense * float(angle)) @ rot
            poses.append(Pose(aim - turned @ mouth, turned))
        err = max(ctx.planner.ik(ctx._seed(arm, p.pos), arm, p)[1] for p in (poses[0], poses[-1]))
        if best is None or err < best[0]:
            best = (err, poses)
    return best[1]


def _dip(here: Pose, head: np.ndarray) -> np.ndarray:
    """The gripper rotation `here.rot` rolled by STRIKE_TILT about its finger axis, in the sense that lowers a
    point `head` (offset from the TCP, world frame)."""
    axis = here.rot[:, 1] / np.linalg.norm(here.rot[:, 1])
    best = None
    for angle in (STRIKE_TILT, -STRIKE_TILT):
        turn = _axis_angle(axis, angle)
        z = float((turn @ head)[2])
        if best is None or z < best[0]:
            best = (z, turn @ here.rot)
    return best[1]


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix of `angle` about the unit `axis` (Rodrigues)."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * k @ k


def run_strike(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    return strike(ctx, step.get("arm", "auto"), step["object"], step["target"])


def run_pour(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    return pour(ctx, step.get("arm", "auto"), step["object"], step["target"])
