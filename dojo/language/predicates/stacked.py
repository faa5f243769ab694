"""stacked([a, b, c, ...]): a stack from bottom to top, i.e. on(b, a) and on(c, b) and ..."""

from __future__ import annotations

from itertools import pairwise

from dojo.language.predicate_registry import PredicateWord, objref_list, register
from dojo.language.predicates.connectives import AllOf


def compile_stacked(ctx, arg, ref, bound) -> AllOf:
    refs = [ref(r) for r in arg]
    return AllOf(tuple(ctx.node({"on": [top, below]}, bound) for below, top in pairwise(refs)))


register(PredicateWord("stacked", objref_list("[a, b, c, ...]: a stack from bottom to top.", 2), compile_stacked))
