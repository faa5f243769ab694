"""inside(a, container): a's centre is within the container's `inside` placement box (else its bounding box);
a region counts as a box REGION_HEIGHT tall above its surface."""

from __future__ import annotations

from dataclasses import dataclass

from dojo.backends import predicates as P

from dojo.language.predicate_registry import PredicateWord, objref_list, register


@dataclass(frozen=True)
class Inside:
    a: int
    container: int
    up: float


def compile_inside(ctx, arg, ref, bound) -> Inside:
    a, c = ref(arg[0]), ref(arg[1])
    up = P.REGION_HEIGHT if ctx.is_region(c) else 0.0
    return Inside(ctx.frame(a), ctx.annotated_frame(c, "inside"), up)


def evaluate_inside(ev, node: Inside):
    return P.inside(ev.xp, ev.frame(node.a), ev.frame(node.container), node.up)


register(PredicateWord("inside", objref_list("[a, container]: a is within the container's placement region.", 2, 2),
                       compile_inside, Inside, evaluate_inside))
