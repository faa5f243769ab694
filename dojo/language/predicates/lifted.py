"""lifted(a, h): a's centre is at least h metres above where it was at the start of the episode."""

from __future__ import annotations

from dataclasses import dataclass

from dojo.backends import predicates as P

from dojo.language.predicate_registry import PredicateWord, ref_and_number, register


@dataclass(frozen=True)
class Lifted:
    a: int
    height: float


def compile_lifted(ctx, arg, ref, bound) -> Lifted:
    return Lifted(ctx.frame(ref(arg[0])), float(arg[1]))


def evaluate_lifted(ev, node: Lifted):
    pos, mat, c, _ = ev.frame(node.a)
    return P.lifted(ev.xp, pos, mat, c, ev.params["init_center"][:, node.a], node.height)


register(PredicateWord("lifted", ref_and_number("[a, height]: a is at least height metres above its initial height."),
                       compile_lifted, Lifted, evaluate_lifted))
