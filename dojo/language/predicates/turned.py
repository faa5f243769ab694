"""turned(object/joint, angle): a hinge (a lock's cylinder, a dial) stands at least `angle` degrees, either way,
from where it was at the start of the episode.

A key is turned by turning what it sits in: the lock's cylinder, whose joint the key drives once it is seated
(and which a task may keep locked until then: events lock/unlock with `plugged`). Reading the joint rather than
the key's own attitude means a key twisted in the air, or forced round outside the keyway, turns nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from dojo.language.predicate_registry import PredicateWord, ref_and_number, register


@dataclass(frozen=True)
class Turned:
    joint: int
    """The joint's column in `state["qpos"]`."""
    start: float
    """Its position at the start of the episode (the plan's initial state)."""
    angle: float
    """Radians."""


def compile_turned(ctx, arg, ref, bound) -> Turned:
    name = ref(arg[0])
    column = ctx.joint(name)  # checks the name, with the object's joints listed when it is wrong
    start = float(ctx.data.qpos[ctx.model.joint(name).qposadr[0]])
    return Turned(column, start, math.radians(float(arg[1])))


def evaluate_turned(ev, node: Turned):
    return ev.xp.abs(ev.state["qpos"][:, node.joint] - node.start) >= node.angle


register(PredicateWord(
    "turned",
    ref_and_number("[object/joint, angle]: the hinge stands at least angle degrees (either way) from where it was "
                   "at the start of the episode (a lock's cylinder turned by its key). Example: "
                   "{turned: [lock/plug, 80]}."),
    compile_turned, Turned, evaluate_turned))
