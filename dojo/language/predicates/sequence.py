"""sequence([p, q, ...]): each listed predicate became true (turned from false to true) after the one before it
did, the first one at any time (true from the start counts). Unlike `ordered`, which compares the first steps
the children held, a child that was already true before its predecessor turned true, and stays so, never counts:
"uncover red, then green" fails when green was uncovered first. Memory per child: the step it turned true in
order (-1 = not yet) and whether it held at the previous step."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from dojo.language.predicate_registry import PREDICATE, PredicateWord, register

SCHEMA = {"description": "Each listed predicate turned true (from false) after the one before it did; the first may "
                         "hold from the start. E.g. [{pressed: [button, 1]}, {on: [block, mat]}]: the block was put "
                         "on the mat after the press.",
          "type": "array", "items": {"$ref": PREDICATE}, "minItems": 2}


@dataclass(frozen=True)
class Sequence:
    children: tuple[Any, ...]
    first: int
    """Slot of the first child's turn step in memory["first"]; then each child's turn step, then each child's
    value at the previous step (0/1, -1 before the first step)."""


def compile_sequence(ctx, arg, ref, bound) -> Sequence:
    children = tuple(ctx.node(p, bound) for p in arg)
    return Sequence(children, ctx.order_slots(2 * len(children)))


def evaluate_sequence(ev, node: Sequence):
    xp = ev.xp
    n = len(node.children)
    done = xp.ones((ev.n,), dtype=bool)
    for k, child in enumerate(node.children):
        turned = ev.memory["first"][:, node.first + k]
        was = ev.memory["first"][:, node.first + n + k]
        now = ev.eval(child)
        rising = now & ((was == 0) | ((was < 0) & (k == 0)))  # the first child may hold from the start
        turned = xp.where((turned < 0) & done & rising, ev.step, turned)
        ev.record_first(node.first + k, turned)
        ev.record_first(node.first + n + k, now.astype(turned.dtype))
        done = turned >= 0
    return done


register(PredicateWord("sequence", SCHEMA, compile_sequence, Sequence, evaluate_sequence))
