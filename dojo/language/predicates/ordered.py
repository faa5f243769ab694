"""ordered([p, q, ...]): the listed predicates first became true in this order (children first true in the same
step count as in order). The first step of each child is memory, so the order survives a child turning false."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise
from typing import Any

from dojo.language.predicate_registry import PREDICATE, PredicateWord, register

SCHEMA = {"description": "The listed predicates first became true in this order.", "type": "array",
          "items": {"$ref": PREDICATE}, "minItems": 2}


@dataclass(frozen=True)
class Ordered:
    children: tuple[Any, ...]
    first: int
    """Slot of the first child in memory["first"]; the children use consecutive slots."""


def compile_ordered(ctx, arg, ref, bound) -> Ordered:
    children = tuple(ctx.node(p, bound) for p in arg)
    return Ordered(children, ctx.order_slots(len(children)))


def evaluate_ordered(ev, node: Ordered):
    xp = ev.xp
    firsts = []
    for k, child in enumerate(node.children):
        prev = ev.memory["first"][:, node.first + k]
        firsts.append(xp.where((prev < 0) & ev.eval(child), ev.step, prev))
        ev.record_first(node.first + k, firsts[-1])
    seen = xp.all(xp.stack([f >= 0 for f in firsts], axis=-1), axis=-1)
    in_order = xp.all(xp.stack([a <= b for a, b in pairwise(firsts)], axis=-1), axis=-1)
    return seen & in_order


register(PredicateWord("ordered", SCHEMA, compile_ordered, Ordered, evaluate_ordered))
