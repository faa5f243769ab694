"""struck(object/joint, min_speed): the part on that joint (a xylophone bar, a drum skin) was hit: at some
control step since the episode started the joint moved from its rest position towards the far end of its range
at min_speed or faster (m/s for a slide, rad/s for a hinge).

A strike is told from a touch by speed, not by contact: a mallet resting on a bar, or pressing it down slowly,
deflects the bar but does not move it fast, while a hit drives it down at the striker's speed. The joint has a
spring holding it at one end of its range (the asset's rest), so it moves only when something hits it. The
first step the condition held is kept in the program's memory (an `ordered` slot), so a strike counts after
the bar has come back up and `ordered([struck(a, v), struck(b, v)])` compares first strikes."""

from __future__ import annotations

from dataclasses import dataclass

from dojo.language.predicate_registry import PredicateWord, ref_and_number, register


@dataclass(frozen=True)
class Struck:
    dof: int
    """The joint's column in `state["qvel"]` (`StateIndex.dof_adr` holds its velocity address in the model)."""
    direction: float
    """+1 or -1: the sign of a velocity from the rest position towards the far end of the range."""
    min_speed: float
    slot: int
    """Memory slot (`memory["first"]`) of the first step the joint moved that fast."""


def compile_struck(ctx, arg, ref, bound) -> Struck:
    name = ref(arg[0])
    column = ctx.joint_speed(name)  # checks the name, with the object's joints listed when it is wrong
    joint = ctx.model.joint(name)
    lo, hi = (float(v) for v in ctx.model.jnt_range[joint.id])
    rest = min(max(float(ctx.data.qpos[joint.qposadr[0]]), lo), hi)
    direction = -1.0 if abs(lo - rest) >= abs(hi - rest) else 1.0
    return Struck(column, direction, float(arg[1]), ctx.order_slots(1))


def evaluate_struck(ev, node: Struck):
    xp = ev.xp
    prev = ev.memory["first"][:, node.slot]
    hit = ev.state["qvel"][:, node.dof] * node.direction >= node.min_speed
    first = xp.where((prev < 0) & hit, ev.step, prev)
    ev.record_first(node.slot, first)
    return first >= 0


register(PredicateWord(
    "struck",
    ref_and_number("[object/joint, min_speed]: the part on that sprung joint was hit (moved from its rest "
                   "towards the far end of its range at min_speed or faster) at some step of the episode."),
    compile_struck, Struck, evaluate_struck))
