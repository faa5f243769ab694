"""`place_free`: a board game's move, putting a piece on the first free one of a board's places.

The places are placement annotations of the target (a tic-tac-toe board's `cell_*`), tried in the order the step
lists them; a place is free when no other object's footprint centre lies on it (the expert sees the board as the
robot does, with the opponent's pieces on it).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dojo.experts.skills import SkillContext, SkillFailed, SkillGen, place

MARGIN = 0.01
"""An object's centre this far outside a place's box in the plane still takes the place (m)."""


def free_place(ctx: SkillContext, obj: str, target: str, places: list[str]) -> str:
    """The first of `places` (annotations of `target`) that no object other than `obj` lies on."""
    others = [ctx.scene.box(n).center for n in ctx.scene.others((obj, target))]
    for name in places:
        site = ctx.scene.site(target, name)
        if not any(np.all(np.abs(site.rot.T @ (c - site.center))[:2] <= site.half[:2] + MARGIN)
                   and abs(float(c[2] - site.center[2])) < 0.05 for c in others):
            return f"{target}/{name}"
    raise SkillFailed(f"no free place on {target} among {', '.join(places)}")


def run_place_free(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    target = free_place(ctx, step["object"], step["target"], list(step["places"]))
    return place(ctx, step.get("arm", "auto"), step["object"], target)
