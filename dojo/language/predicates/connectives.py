"""all([...]), any([...]) and not(p): the boolean connectives. Kept in one module because `stacked` and the
quantifiers compile into the same two nodes."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from dojo.language.predicate_registry import PREDICATE, PredicateWord, register


@dataclass(frozen=True)
class AllOf:
    children: tuple[Any, ...]


@dataclass(frozen=True)
class AnyOf:
    children: tuple[Any, ...]


@dataclass(frozen=True)
class Not:
    child: Any


def _list_schema(description: str) -> dict:
    return {"description": description, "type": "array", "items": {"$ref": PREDICATE}, "minItems": 1}


def compile_all(ctx, arg, ref, bound) -> AllOf:
    return AllOf(tuple(ctx.node(p, bound) for p in arg))


def compile_any(ctx, arg, ref, bound) -> AnyOf:
    return AnyOf(tuple(ctx.node(p, bound) for p in arg))


def compile_not(ctx, arg, ref, bound) -> Not:
    return Not(ctx.node(arg, bound))


def evaluate_all(ev, node: AllOf):
    out = ev.xp.ones((ev.n,), dtype=bool)
    for child in node.children:
        out = out & ev.eval(child)
    return out


def evaluate_any(ev, node: AnyOf):
    out = ev.xp.zeros((ev.n,), dtype=bool)
    for child in node.children:
        out = out | ev.eval(child)
    return out


def evaluate_not(ev, node: Not):
    return ~ev.eval(node.child)


register(PredicateWord("all", _list_schema("Every listed predicate holds."), compile_all, AllOf, evaluate_all))
register(PredicateWord("any", _list_schema("At least one listed predicate holds."), compile_any, AnyOf, evaluate_any))
register(PredicateWord("not", {"description": "The predicate does not hold.", "$ref": PREDICATE},
                       compile_not, Not, evaluate_not))
