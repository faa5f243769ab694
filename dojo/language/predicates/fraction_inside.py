"""fraction_inside(group, container, x): at least the fraction x of the group's objects are inside the container
(each as `inside` judges it: its centre within the container's `inside` placement box). Granular contents (balls
poured from a cup into a vase) are judged by how much arrived, not all-or-nothing: a pour that spills one ball
of twelve still counts at x = 0.9."""

from __future__ import annotations

from dataclasses import dataclass

from dojo.backends import predicates as P
from dojo.backends.program_types import ProgramError

from dojo.language.predicate_registry import OBJREF, PredicateWord, register

SCHEMA = {
    "description": "[group, container, fraction]: at least that fraction (0..1) of the group's objects are inside "
                   "the container's placement region.",
    "type": "array",
    "prefixItems": [{"$ref": "#/$defs/name"}, {"$ref": OBJREF}, {"type": "number", "minimum": 0, "maximum": 1}],
    "items": False,
    "minItems": 3,
}


@dataclass(frozen=True)
class FractionInside:
    members: tuple[int, ...]
    """Frames of the group's objects."""
    container: int
    fraction: float


def compile_fraction_inside(ctx, arg, ref, bound) -> FractionInside:
    members = ctx.group_members(arg[0])
    if not members:
        raise ProgramError(f"fraction_inside: group {arg[0]!r} has no objects")
    return FractionInside(tuple(ctx.frame(m) for m in members), ctx.annotated_frame(ref(arg[1]), "inside"),
                          float(arg[2]))


def evaluate_fraction_inside(ev, node: FractionInside):
    xp = ev.xp
    inside = xp.stack([P.inside(xp, ev.frame(m), ev.frame(node.container)) for m in node.members], axis=-1)
    # count, not mean: the fraction is compared exactly (7 of 10 against 0.7 is not a float rounding question)
    return xp.sum(inside.astype(xp.int32), axis=-1) >= node.fraction * len(node.members) - 1e-9


register(PredicateWord("fraction_inside", SCHEMA, compile_fraction_inside, FractionInside, evaluate_fraction_inside))
