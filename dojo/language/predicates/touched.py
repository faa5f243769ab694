"""touched(a, b): some geom of a is in contact with some geom of b (`robot` is both arms)."""

from __future__ import annotations

from dataclasses import dataclass

from dojo.backends import predicates as P

from dojo.language.predicate_registry import PredicateWord, objref_list, register


@dataclass(frozen=True)
class Touched:
    a: tuple[int, ...]
    b: tuple[int, ...]


def compile_touched(ctx, arg, ref, bound) -> Touched:
    return Touched(ctx.atoms_of(ref(arg[0])), ctx.atoms_of(ref(arg[1])))


def evaluate_touched(ev, node: Touched):
    return P.touched(ev.xp, ev.state["contact"], node.a, node.b)


register(PredicateWord("touched", objref_list("[a, b]: a and b are in contact.", 2, 2),
                       compile_touched, Touched, evaluate_touched))
