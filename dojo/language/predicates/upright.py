"""upright(a): the object's up axis is within UPRIGHT_DEGREES of vertical."""

from __future__ import annotations

from dataclasses import dataclass

from dojo.backends import predicates as P

from dojo.language.predicate_registry import OBJREF, PredicateWord, register


@dataclass(frozen=True)
class Upright:
    a: int


def compile_upright(ctx, arg, ref, bound) -> Upright:
    return Upright(ctx.frame(ref(arg)))


def evaluate_upright(ev, node: Upright):
    return P.upright(ev.xp, ev.state["mat"][:, node.a])


register(PredicateWord("upright", {"description": "The object's up axis is within 15 degrees of vertical.",
                                   "$ref": OBJREF}, compile_upright, Upright, evaluate_upright))
