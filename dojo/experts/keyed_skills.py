"""Skills of keyed insertion: `plug` (a plug's leading point into a socket, its heading turned to the socket's
and the point pushed to the socket's floor: a key into a keyway, a charger's prongs into a power strip) and `turn`
(grip what stands in a socket where it is and turn it about the vertical: a key in its lock).

They differ from `insert` (`dojo.experts.skills`), which lets an object drop into an opening from just above it:
a plug goes in with a clearance under a millimetre and its leading end first, so the skill measures that end
(the object's `tip` annotation), not the object's centre, and aims it at the entrance before pushing it in.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from dojo.experts.motion import SLOW, Pose
from dojo.experts.precision_skills import held_arm
from dojo.experts.skills import (
    GRIP_STEPS,
    RELEASE_STEPS,
    SkillContext,
    SkillFailed,
    SkillGen,
    carry_to,
    free_other_arm,
    give_up_fit,
    grasp_frame,
    grasp_height,
    open_and_retreat,
    pushed_in,
)

PLUG_LEAD = 0.004
"""Height (m) of the plug's tip above the socket's entrance while it is aimed."""
PLUG_AIM_TOL = 0.0005
PLUG_YAW_TOL = math.radians(3.0)
PLUG_AIMS = 4
"""A tip turned more than PLUG_YAW_TOL from the socket's heading is turned once more (a smaller turn is left alone:
the prongs' play takes a few degrees, and near the end of its wrist's range the arm trades millimetres of position
for a degree of attitude); then a tip found farther than PLUG_AIM_TOL (m) from its aim is moved, at most
PLUG_AIMS times, before it goes in."""
PLUG_SPEED = 0.03
"""Commanded TCP speed (m/s) of the push into the socket."""
PLUG_CLEAR = 0.001
"""The push ends with the tip this far (m) above the socket's floor; released there, the plug settles onto it."""
TURN_PARTS = 3
"""A turn is made in this many moves, each ending at rest, so the gripped part follows the fingers."""
TURN_SETTLE = 6
TURN_ABOVE = 0.05
"""Height (m) above the grip from which the fingers come down onto the object and to which they go back."""
TURN_GRIPS = 4
TURN_DONE = math.radians(2.0)
"""The turn is measured on the object itself (a key lags the fingers by its play in the keyway and in the grip):
grips follow one another until it has turned to within TURN_DONE (rad) of the angle asked, at most TURN_GRIPS."""
TURN_SHARES = (1.0, 0.75, 0.5, 0.35)
"""Shares of the remaining turn tried from a grip, largest first; at most TURN_GRIPS grips."""
TURN_REACH = 0.003
TURN_ROT_TOL = 0.03
"""Position (m) and attitude (rad) errors within which the arm reaches a turned pose."""


def plug(ctx: SkillContext, arm: str, obj: str, target: str) -> SkillGen:
    """Put `obj`'s leading point (its `tip` annotation) into the socket `target` (an `object/annotation` box from
    its entrance, the top, to its floor): grasp unless held, carry it over the entrance with its heading turned to
    the socket's (as an axis: the smaller turn), measure the tip and correct its position and heading until it is
    within a fraction of a millimetre of its aim, push it a few millimetres in and, once it is in, down to the
    floor slowly; let go and back off. A tip that did not get in is put back (`give_up_fit`)."""
    if "/" not in target:
        raise SkillFailed(f"plug: target {target!r} is not an object/annotation socket")
    if not ctx.scene.has_site(obj, "tip"):
        raise SkillFailed(f"plug: {obj} has no `tip` annotation to lead with")
    a = yield from held_arm(ctx, obj, arm)
    socket = ctx.scene.site(*target.split("/", 1))
    floor = ctx.scene.target(target).point
    aim = floor + socket.rot[:, 2] * (2.0 * socket.half[2] + PLUG_LEAD)
    tip = ctx.scene.site(obj, "tip")
    turn = axis_turn(tip.rot, socket.rot)
    offset = _rotate_z(ctx.scene.box(obj).center - tip.center, turn)
    yield from carry_to(ctx, a, obj, aim + offset, yaw_change=turn, release=False, speed_down=SLOW / 2, precise=True)
    yield from _aim(ctx, a, obj, socket, aim)
    # in by a few millimetres first: a tip that does not enter (it stands on the socket's rim) is not forced
    entrance = float(aim[2]) - PLUG_LEAD
    if not (yield from pushed_in(ctx, a, lambda: ctx.scene.site(obj, "tip").center, entrance, PLUG_SPEED)):
        yield from give_up_fit(ctx, a, obj, target)
    depth = float(ctx.scene.site(obj, "tip").center[2] - floor[2]) - PLUG_CLEAR
    yield ctx.line(a, ctx.tcp(a).shifted([0.0, 0.0, -depth]), PLUG_SPEED, settle=10)
    yield from open_and_retreat(ctx, a)


def _aim(ctx: SkillContext, a: int, obj: str, socket: Any, aim: np.ndarray) -> SkillGen:
    """Bring the held object's tip to `aim` (above the socket's entrance), its heading to the socket's."""
    tip = ctx.scene.site(obj, "tip")
    yaw = axis_turn(tip.rot, socket.rot)
    if abs(yaw) >= PLUG_YAW_TOL:  # turned first: the position is measured and corrected after
        yield ctx.line(a, turned_about(ctx.tcp(a), tip.center, yaw), SLOW / 4, settle=10)
    for _ in range(PLUG_AIMS):
        error = aim - ctx.scene.site(obj, "tip").center
        if float(np.linalg.norm(error[:2])) < PLUG_AIM_TOL:
            break
        yield ctx.line(a, ctx.tcp(a).shifted(error), SLOW / 4, settle=10)


def turn(ctx: SkillContext, arm: str, obj: str, angle: float) -> SkillGen:
    """Grip `obj` where it stands (top-down at its grasp annotation, without lifting it: a key in a lock) and turn
    it `angle` degrees about the vertical through its `tip` (else its centre), counter-clockwise seen from above,
    as measured on the object; then let go and back off. A wrist turns only so far: the turn is made in as few
    grips as the arm allows, each taking the object the way that leaves the wrist the most room."""
    a = ctx.choose_arm(arm, ctx.scene.box(obj).center)
    yield from free_other_arm(ctx, a)
    goal, start = math.radians(angle), _heading(ctx, obj)
    for _ in range(TURN_GRIPS):
        remaining = goal - _wrap(_heading(ctx, obj) - start)
        if abs(remaining) < TURN_DONE:
            return
        pivot = ctx.scene.site(obj, "tip").center if ctx.scene.has_site(obj, "tip") else ctx.scene.box(obj).center
        grip, part, width = _turn_grip(ctx, a, obj, pivot, remaining)
        yield ctx.gripper(a, min(1.0, (width + 0.03) / ctx.max_width), 1)
        yield ctx.line(a, grip.shifted([0.0, 0.0, TURN_ABOVE]), SLOW * 2)
        yield ctx.line(a, grip, SLOW)
        yield ctx.gripper(a, 0.0, GRIP_STEPS)
        for k in range(1, TURN_PARTS + 1):
            yield ctx.line(a, turned_about(grip, pivot, part * k / TURN_PARTS), SLOW, settle=TURN_SETTLE)
        yield ctx.gripper(a, 1.0, RELEASE_STEPS)
        yield ctx.line(a, ctx.tcp(a).shifted([0.0, 0.0, TURN_ABOVE]), SLOW * 2, settle=0)
    remaining = goal - _wrap(_heading(ctx, obj) - start)
    if abs(remaining) >= TURN_DONE:
        raise SkillFailed(f"turn: {obj} still {math.degrees(remaining):.0f} degrees short after {TURN_GRIPS} grips")


def _heading(ctx: SkillContext, obj: str) -> float:
    """The object's heading about the vertical (rad): its `tip` frame's x axis, else its body's."""
    rot = ctx.scene.site(obj, "tip").rot if ctx.scene.has_site(obj, "tip") else ctx.scene.box(obj).rot
    return math.atan2(rot[1, 0], rot[0, 0])


def _wrap(a: float) -> float:
    return math.atan2(math.sin(a), math.cos(a))


def _turn_grip(ctx: SkillContext, a: int, obj: str, pivot: np.ndarray, remaining: float
               ) -> tuple[Pose, float, float]:
    """The grip to turn `obj` from (a top-down pose at its grasp region), how far (rad, up to `remaining`) the arm
    turns it from there, and the opening the fingers need. The fingers may close across either horizontal axis of
    the grasp region where the object fits between them, from either side: four grips a quarter turn apart, of
    which the one the wrist turns farthest from is taken (a wrist roll spans half a turn, so one of them always
    leaves it a quarter turn)."""
    region, _ = grasp_frame(ctx, obj)
    point = np.array([*region.center[:2], grasp_height(ctx, obj)])
    best: tuple[Pose, float, float] | None = None
    for k in range(2):
        axis = np.array([region.rot[0, k], region.rot[1, k], 0.0])
        if np.linalg.norm(axis) < 0.5:
            continue
        axis /= np.linalg.norm(axis)
        width = ctx.scene.width_through(obj, region.center, axis)
        if width > ctx.max_width - 0.012:
            continue
        for sign in (1.0, -1.0):
            pose = ctx.reachable(a, point, sign * axis)
            q, err = ctx.planner.ik(ctx._seed(a, pose.pos), a, pose)
            if err > TURN_REACH:
                continue
            share = next((f for f in TURN_SHARES if _reaches(ctx, a, q, turned_about(pose, pivot, remaining * f))),
                         0.0)
            if share > 0.0 and (best is None or share > best[1]):
                best = (pose, share, width)
    if best is None:
        raise SkillFailed(f"turn: the arm cannot turn {obj} from any grip")
    return best[0], remaining * best[1], best[2]


def _reaches(ctx: SkillContext, a: int, q: np.ndarray, goal: Pose) -> bool:
    """Whether the arm, from joints q, reaches `goal` in position and attitude."""
    end, err = ctx.planner.ik(q, a, goal)
    return err < TURN_REACH and _angle(ctx.planner.fk(end, a).rot, goal.rot) < TURN_ROT_TOL


def axis_turn(rot: np.ndarray, target: np.ndarray) -> float:
    """The turn about the vertical (rad, within a quarter turn either way) that brings the x axis of `rot` onto
    that of `target` as an axis (a direction or its opposite)."""
    d = math.atan2(target[1, 0], target[0, 0]) - math.atan2(rot[1, 0], rot[0, 0])
    return math.atan2(math.sin(2.0 * d), math.cos(2.0 * d)) / 2.0


def turned_about(pose: Pose, pivot: np.ndarray, angle: float) -> Pose:
    """`pose` turned `angle` rad about the vertical line through `pivot`."""
    c, s = math.cos(angle), math.sin(angle)
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    centre = np.array([pivot[0], pivot[1], pose.pos[2]])
    return Pose(centre + rz @ (pose.pos - centre), rz @ pose.rot)


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return math.acos(max(-1.0, min(1.0, (float(np.trace(a.T @ b)) - 1.0) / 2.0)))


def _rotate_z(v: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]])


def run_plug(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    return plug(ctx, step.get("arm", "auto"), step["object"], step["target"])


def run_turn(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    return turn(ctx, step.get("arm", "auto"), step["object"], float(step["angle"]))
