"""on(a, b): a rests on top of b (on b's `top` placement box when it has one), touching it unless b is a region."""

from __future__ import annotations

from dataclasses import dataclass

from dojo.backends import predicates as P

from dojo.language.predicate_registry import PredicateWord, objref_list, register


@dataclass(frozen=True)
class On:
    a: int
    support: int
    touch: tuple[tuple[int, ...], tuple[int, ...]] | None
    """Atoms of a and b that must touch; None when b is a region (nothing to touch)."""


def compile_on(ctx, arg, ref, bound) -> On:
    a, b = ref(arg[0]), ref(arg[1])
    touch = None if ctx.is_region(b) else (ctx.atoms_of(a), ctx.atoms_of(b))
    return On(ctx.frame(a), ctx.annotated_frame(b, "top"), touch)


def evaluate_on(ev, node: On):
    return P.on(ev.xp, ev.frame(node.a), ev.frame(node.support), ev.touching(node.touch))


register(PredicateWord("on", objref_list("[a, b]: a rests on top of b.", 2, 2), compile_on, On, evaluate_on))
