"""`lift`: raise an object to a height above the table and set it down again where it stood (a basket lifted to
show it is empty, then back in its place for the next steps)."""

from __future__ import annotations

from typing import Any

from dojo.experts.skills import SkillContext, SkillGen, carry_to, push_up


def lift(ctx: SkillContext, arm: str, obj: str, height: float) -> SkillGen:
    before = ctx.scene.box(obj).center.copy()
    yield from push_up(ctx, arm, obj, height)
    a = next(k for k, held in ctx.held.items() if held == obj)
    yield from carry_to(ctx, a, obj, before + [0.0, 0.0, 0.004])


def run_lift(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    return lift(ctx, step.get("arm", "auto"), step["object"], float(step.get("height", 0.1)))
