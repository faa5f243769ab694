"""near(a, b, d): a's centre is within d metres of b's (in the ground plane when b is a region)."""

from __future__ import annotations

from dataclasses import dataclass

from dojo.backends import predicates as P

from dojo.language.predicate_registry import OBJREF, PredicateWord, register

SCHEMA = {
    "description": "[a, b, distance]: a's centre is within distance metres of b's.",
    "type": "array",
    "prefixItems": [{"$ref": OBJREF}, {"$ref": OBJREF}, {"type": "number"}],
    "items": False,
    "minItems": 3,
}


@dataclass(frozen=True)
class Near:
    a: int
    b: int
    distance: float
    planar: bool


def compile_near(ctx, arg, ref, bound) -> Near:
    b = ref(arg[1])
    return Near(ctx.frame(ref(arg[0])), ctx.frame(b), float(arg[2]), ctx.is_region(b))


def evaluate_near(ev, node: Near):
    return P.near(ev.xp, ev.frame(node.a), ev.frame(node.b), node.distance, node.planar)


register(PredicateWord("near", SCHEMA, compile_near, Near, evaluate_near))
