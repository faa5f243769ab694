"""`lift`: raise an object to a height above the table and set it down again where it stood (a basket lifted to
show it is empty, then back in its place for the next steps): grasped, lifted, brought back down the way it went
up to the pose it was grasped in, let go."""

from __future__ import annotations

from typing import Any

from dojo.experts.motion import SLOW
from dojo.experts.skills import (
    APPROACH,
    SkillContext,
    SkillGen,
    free_other_arm,
    grasp,
    open_and_retreat,
    push_up,
)


def lift(ctx: SkillContext, arm: str, obj: str, height: float) -> SkillGen:
    a = ctx.choose_arm(arm, ctx.scene.box(obj).center)
    yield from free_other_arm(ctx, a)
    yield from grasp(ctx, a, obj)
    down = ctx.tcp(a).shifted([0.0, 0.0, -APPROACH])  # grasp() ends lifted clear: where it closed on the object
    yield from push_up(ctx, arm, obj, height)
    yield ctx.line(a, down.shifted([0.0, 0.0, 0.004]), SLOW, settle=6)
    yield from open_and_retreat(ctx, a)


def run_lift(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    return lift(ctx, step.get("arm", "auto"), step["object"], float(step.get("height", 0.1)))
