"""The skill `screw`: fasten a screw in a thread (an asset's `threads:` entry, `tightened` in the task language).

A parallel gripper cannot spin a screw, so it turns it the way a hand with a wrench does: grasp the head by its
flats, turn a quarter turn (the wrist rolls about the thread's axis while the gripper follows the screw down by
the pitch), let go, turn back open, grasp again, until the thread has turned as far as asked. Each quarter starts
from the flats' grasp whose turn is centred on the unrolled wrist (a quarter either side of it), so the wrist
stays inside its range however many turns are asked. The thread's axis, sense and pitch are read from the model
(the hinge the socket rides on and its joint equality), not from the task: any threaded asset works.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from dojo.experts.motion import SLOW, Pose
from dojo.experts.skills import (
    GRIP_STEPS,
    RELEASE_STEPS,
    SkillContext,
    SkillFailed,
    SkillGen,
    carry_to,
    free_other_arm,
    grasp,
    grasp_height,
    open_and_retreat,
)

QUARTER = math.pi / 2
"""Turn (rad) per grasp: a square head's flats come round to the fingers again after a quarter turn."""
TURN_MARGIN = 0.05
"""Turns past the asked number the skill aims for (a thread's equality constraint is soft: it lags a little)."""
EXTRA_GRASPS = 3
"""Grasps allowed beyond the quarters the turns need (a grasp that slipped is made up for)."""
ABOVE_SEAT = 0.004
"""Height (m) of the screw's tip above the socket's floor where it is let go into the socket."""
TURN_SETTLE = 4
"""Control steps held at the end of each quarter turn, for the thread to follow."""


@dataclass(frozen=True)
class Thread:
    """A thread as the model holds it: the hinge's qpos address, its rest and tightening sense, its world axis,
    and the slide's world axis and advance per radian."""

    qpos: int
    rest: float
    direction: float
    axis: np.ndarray
    slide_axis: np.ndarray
    ratio: float


def thread_at(ctx: SkillContext, obj: str, annotation: str) -> Thread:
    """The thread whose hinge turns the link carrying `obj`'s annotation (the socket)."""
    model, data = ctx.model, ctx.data
    body = int(model.site_bodyid[model.site(ctx.plan.objects[obj]["sites"][annotation]).id])
    hinges = [j for j in range(model.body_jntadr[body], model.body_jntadr[body] + model.body_jntnum[body])
              if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
    coupling = next(((j, e) for j in hinges for e in range(model.neq)
                     if model.eq_type[e] == mujoco.mjtEq.mjEQ_JOINT and model.eq_obj2id[e] == j), None)
    if coupling is None:
        raise SkillFailed(f"screw: {obj}/{annotation} is on no thread (a hinge coupled to a slide)")
    hinge, eq = coupling
    slide = int(model.eq_obj1id[eq])
    lo, hi = (float(v) for v in model.jnt_range[hinge])
    adr = int(model.jnt_qposadr[hinge])
    rest = min(max(float(ctx.plan.init_qpos[adr]), lo), hi)
    direction = -1.0 if abs(lo - rest) >= abs(hi - rest) else 1.0
    return Thread(adr, rest, direction, data.xaxis[hinge].copy(), data.xaxis[slide].copy(), float(model.eq_data[eq, 1]))


def turned(ctx: SkillContext, thread: Thread) -> float:
    """Full turns the thread has turned in its tightening sense."""
    return (float(ctx.data.qpos[thread.qpos]) - thread.rest) * thread.direction / (2.0 * math.pi)


def _flats(ctx: SkillContext, arm: int, obj: str, point: np.ndarray, turn: np.ndarray) -> np.ndarray:
    """The finger axis across the head's flats (one of its horizontal axes, either way round) whose quarter turn
    `turn` is centred on the unrolled wrist's axis."""
    rot = ctx.scene.box(obj).rot
    natural = ctx.natural_axis(arm, point)
    half = Rotation.from_matrix(turn).as_rotvec() / 2.0
    middle = Rotation.from_rotvec(half).as_matrix()
    candidates = [s * rot[:, k] for k in range(2) for s in (1.0, -1.0)]
    best = max(candidates, key=lambda axis: float((middle @ axis) @ natural))
    return np.array([best[0], best[1], 0.0]) / max(float(np.linalg.norm(best[:2])), 1e-9)


def screw(ctx: SkillContext, arm: str, obj: str, target: str, turns: float) -> SkillGen:
    """Fasten `obj` in the thread whose socket is `target` (`object/annotation`, a placement box on the thread's
    hinge link): grasp it unless held, bring it over the socket with its square turned to the socket's, lower it
    in, then turn it `turns` full turns, a quarter per grasp (module docstring)."""
    if "/" not in target:
        raise SkillFailed(f"screw: target {target!r} is not an object/annotation socket")
    owner, annotation = target.split("/", 1)
    thread = thread_at(ctx, owner, annotation)
    socket = ctx.scene.target(target)
    a = next((k for k, held in ctx.held.items() if held == obj), None)
    if a is None:  # the arm nearer the farther end: the one that reaches the socket top-down, a screw held upright
        a = ctx.choose_arm(arm, ctx.scene.box(obj).center, socket.point)
        yield from free_other_arm(ctx, a)
        yield from grasp(ctx, a, obj)
    box = ctx.scene.box(obj)
    height = float(np.abs(box.rot[2]) @ box.half)
    goal = socket.point + [0.0, 0.0, height + ABOVE_SEAT]
    yield from carry_to(ctx, a, obj, goal, yaw_change=_square_yaw(ctx, a, goal, ctx.scene.site(owner, annotation).rot,
                                                                  box.rot), release=False, speed_down=SLOW / 2,
                        precise=True)
    turn = Rotation.from_rotvec(thread.axis * thread.direction * QUARTER).as_matrix()
    sink = thread.slide_axis * thread.ratio * QUARTER
    region = ctx.scene.site(obj, "grasp") if ctx.scene.has_site(obj, "grasp") else box
    width = 2.0 * float(np.max(region.half[:2])) * math.sqrt(2.0)  # the head's diagonal sweeps past open fingers
    opening = min(1.0, (width + 0.01) / ctx.max_width)
    for _ in range(math.ceil(turns * 4) + EXTRA_GRASPS):
        if turned(ctx, thread) >= turns + TURN_MARGIN:
            break
        yield ctx.gripper(a, opening, RELEASE_STEPS)
        ctx.held.pop(a, None)
        centre = ctx.scene.site(obj, "grasp").center if ctx.scene.has_site(obj, "grasp") else ctx.scene.box(obj).center
        point = np.array([centre[0], centre[1], grasp_height(ctx, obj)])
        start = Pose(point, ctx.orientation(a, point, _flats(ctx, a, obj, point, turn), 0.0))
        yield ctx.line(a, start, SLOW, settle=2)
        yield ctx.gripper(a, 0.0, GRIP_STEPS)
        ctx.held[a] = obj
        yield ctx.line(a, Pose(point + sink, turn @ start.rot), SLOW, settle=TURN_SETTLE)
    if turned(ctx, thread) < turns:
        ctx.failures.append(f"screw: {obj} turned {turned(ctx, thread):.2f} of {turns} turns")
    yield from open_and_retreat(ctx, a)


def _square_yaw(ctx: SkillContext, arm: int, goal: np.ndarray, socket: np.ndarray, held: np.ndarray) -> float:
    """The turn about z that lines a held square's sides up with a square socket's: of the four that do, the one
    that leaves the fingers nearest the unrolled wrist's axis at `goal` (a wrist rolled near the end of its range
    does not reach top-down, and a tilted screw does not go in)."""
    angle = math.atan2(socket[1, 0], socket[0, 0]) - math.atan2(held[1, 0], held[0, 0])
    least = (angle + QUARTER / 2) % QUARTER - QUARTER / 2
    fingers, natural = ctx.tcp(arm).rot[:, 1], ctx.natural_axis(arm, goal)

    def misalignment(turn: float) -> tuple[float, float]:
        c, s = math.cos(turn), math.sin(turn)
        axis = np.array([c * fingers[0] - s * fingers[1], s * fingers[0] + c * fingers[1]])
        return -float(axis @ natural[:2]) / max(float(np.linalg.norm(axis)), 1e-9), abs(turn)

    # signed: a turn that left the fingers reversed would be turned half round again by carry_to, the long way
    return min((least + k * QUARTER for k in (-2, -1, 0, 1, 2)), key=misalignment)


def run_screw(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    return screw(ctx, step.get("arm", "auto"), step["object"], step["target"], float(step.get("turns", 1.0)))
