"""Skills for a world that moves by itself: `catch`, picking an object off a moving conveyor belt by interception.

The expert knows what the robot could see: where the object is now and how the belt moves (its direction and
speed are the plan's drawn conveyor, the same motion a camera shows). It waits, gripper open above a point of the
belt's centre line within its reach and high enough for every item to pass below (it first rises straight up clear
of what stands below it, as `retreat` does), until the object comes near;
then it goes down with its fingers either side of the belt, lets the object ride in between and closes.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dojo.experts.motion import FAST, SLOW, Pose
from dojo.experts.skills import (
    GRIP_STEPS,
    PALM,
    SkillContext,
    SkillFailed,
    SkillGen,
    carry_to,
    grasp_frame,
    grasp_height,
    place_center,
    retreat,
)

INTERCEPT = 0.2
"""Where the gripper waits: this far downstream of the belt's middle (m), within reach of one arm."""
HOVER = 0.2
"""Height of the waiting TCP above the object's grasp height (m): every item passes below it."""
LEAD = 0.1
"""How far upstream of the waiting point the object is when the gripper starts down (m)."""
MARGIN = 0.03
"""Room left to each side between the open fingers and the object riding in (m)."""
ON_BELT = 0.02
"""An object within this of the belt's surface height is on the belt (m)."""
PALM_CLEARANCE = 0.01
"""Room between the palm and the top of the object riding in between the fingers (m)."""
PATIENCE = 5000
"""Control steps the skill waits for the object at most before giving up."""


def _conveyor(plan: Any, obj: str) -> dict[str, Any]:
    """The plan's conveyor (its drawn spec) that carries `obj`."""
    for actor in plan.program.get("actors", []):
        spec = actor.get("conveyor")
        if spec is not None and obj in spec["items"]:
            return spec
    raise SkillFailed(f"no conveyor carries {obj}")


def catch(ctx: SkillContext, arm: str, obj: str, target: str | None = None) -> SkillGen:
    """Pick `obj` off the belt that carries it (see the module docstring); the object is held, lifted, after, or
    put at `target` when one is given."""
    spec = _conveyor(ctx.plan, obj)
    d = np.asarray(spec.get("direction", [1.0, 0.0]), dtype=float)
    d = np.array([*(d / np.linalg.norm(d)), 0.0])
    centre = ctx.scene.target(spec["belt"]).point
    wait_at = centre + d * INTERCEPT
    a = ctx.choose_arm(arm, wait_at)
    across = np.array([-d[1], d[0], 0.0])
    surface = float(centre[2])

    def along() -> float:
        return float((ctx.scene.box(obj).center - centre) @ d)

    for _ in range(PATIENCE):  # until the object is on the belt, upstream of the waiting point
        box = ctx.scene.box(obj)
        if abs(box.bottom - surface) < ON_BELT and along() < INTERCEPT:
            break
        yield ctx.hold(2)
    else:
        raise SkillFailed(f"{obj} never came along the belt")
    region_box, _ = grasp_frame(ctx, obj)
    offset = float((region_box.center - ctx.scene.box(obj).center) @ d)  # grasp point ahead of the box centre
    width = ctx.scene.width_through(obj, region_box.center, across)
    opening = min(1.0, (width + 2 * MARGIN) / ctx.max_width)
    # the palm clears the object's top: it rides in sideways, where a top-down grasp would come down on it
    z = max(grasp_height(ctx, obj), ctx.scene.box(obj).top - PALM + PALM_CLEARANCE)
    point = np.array([*wait_at[:2], z])
    pose = ctx.reachable(a, point, across if across @ ctx.natural_axis(a, point) >= 0 else -across)
    yield from retreat(ctx, a)  # up clear of what it left below first (a basket's handle it just let go of)
    yield ctx.gripper(a, opening, 1)
    yield ctx.line(a, pose.shifted([0.0, 0.0, HOVER]), FAST, settle=0)
    for _ in range(PATIENCE):  # hover until the object is close
        if INTERCEPT - (along() + offset) < LEAD:
            break
        yield ctx.hold(1)
    yield ctx.line(a, pose, FAST, settle=0)
    for _ in range(PATIENCE):  # fingers either side of the belt: let it ride in
        if along() + offset >= INTERCEPT - 0.004:
            break
        yield ctx.hold(1)
    yield ctx.gripper(a, 0.0, GRIP_STEPS)
    ctx.held[a] = obj
    yield ctx.line(a, Pose(pose.pos + [0.0, 0.0, 0.12], pose.rot), SLOW)
    if target is not None:
        owner = target.split("/", 1)[0] if "/" in target else None
        yield from carry_to(ctx, a, obj, place_center(ctx, a, obj, target), container=owner)


def run_catch(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    return catch(ctx, step.get("arm", "auto"), step["object"], step.get("target"))
