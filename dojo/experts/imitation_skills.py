"""`imitate`: repeat what a demonstrator showed, putting the robot's partner of each of its objects at the target
in the order it moved them. The expert knows that order as the robot saw it (the plan's drawn demonstrator), and
starts only once the demonstrator's last object has come to rest in its container."""

from __future__ import annotations

from typing import Any

import numpy as np

from dojo.language.predicates.same_order_as import demonstrated_order

from dojo.experts.skills import SkillContext, SkillFailed, SkillGen, place

PATIENCE = 3000
"""Control steps to wait for the demonstration to end at most."""


def _demonstration_over(ctx: SkillContext, shown: list[str]) -> bool:
    """Every shown object lies, at rest, inside its demonstrator's container."""
    for actor in ctx.plan.program.get("actors", []):
        spec = actor.get("demonstrator")
        if spec is None or not set(shown) <= set(spec["objects"]):
            continue
        inside = ctx.scene.site(*spec["into"].split("/", 1))
        for name in shown:
            adr = ctx.model.joint(ctx.plan.objects[name]["free_joint"]).dofadr[0]
            offset = np.abs(inside.rot.T @ (ctx.scene.box(name).center - inside.center))
            if np.any(offset > inside.half + 0.02) or np.linalg.norm(ctx.data.qvel[adr:adr + 3]) > 0.01:
                return False
        return True
    raise SkillFailed(f"no demonstrator moves {', '.join(shown)}")


def imitate(ctx: SkillContext, arm: str, pairs: list[list[str]], target: str) -> SkillGen:
    partner = {d: r for d, r in pairs}
    for _ in range(PATIENCE):
        if _demonstration_over(ctx, list(partner)):
            break
        yield ctx.hold(2)
    else:
        raise SkillFailed("the demonstration did not end")
    for shown in demonstrated_order(ctx.plan, list(partner)):
        yield from place(ctx, arm, partner[shown], target)


def run_imitate(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    return imitate(ctx, step.get("arm", "auto"), step["pairs"], step["target"])
