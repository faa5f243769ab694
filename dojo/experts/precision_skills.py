"""Skills of the Precision tasks that the pick-and-place library has no word for: `strike` (a tool's head hits a
target at a set speed: a mallet on a xylophone bar).

Each is a generator of joint-mode segments like the skills of `dojo.experts.skills`, built from the same
primitives (grasp, straight TCP lines, measured corrections), and resumed only when the previous segment has
run, so each move starts from where the held tool really is.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from dojo.experts.motion import CARRY, FAST, Pose
from dojo.experts.skills import SkillContext, SkillFailed, SkillGen, free_other_arm, grasp

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
