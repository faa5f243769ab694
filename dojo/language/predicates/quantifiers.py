"""forall / exists: a predicate over every object of a group, expanded at compile time (`_` is the object).
`forall` of an empty group holds and `exists` of one does not, as in logic."""

from __future__ import annotations

from dojo.language.predicate_registry import QUANTIFIER, PredicateWord, register
from dojo.language.predicates.connectives import AllOf, AnyOf


def compile_forall(ctx, arg, ref, bound) -> AllOf:
    return AllOf(tuple(ctx.node(arg["holds"], m) for m in ctx.group_members(arg["group"])))


def compile_exists(ctx, arg, ref, bound) -> AnyOf:
    return AnyOf(tuple(ctx.node(arg["holds"], m) for m in ctx.group_members(arg["group"])))


register(PredicateWord("forall", {"$ref": QUANTIFIER,
                                  "description": "The predicate holds for every object of the group (`_` is the object)."},
                       compile_forall))
register(PredicateWord("exists", {"$ref": QUANTIFIER, "description": "The predicate holds for at least one object of "
                                                                     "the group (`_` is the object)."},
                       compile_exists))
