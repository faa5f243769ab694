"""aligned(object, target): a planar pose match within a position and a yaw tolerance."""

from __future__ import annotations

from dataclasses import dataclass

from dojo.backends import predicates as P

from dojo.language.predicate_registry import OBJREF, PredicateWord, register

TOLERANCES = {
    "pos_tol": {"description": "Position tolerance in metres.", "type": "number", "exclusiveMinimum": 0,
                "default": 0.02},
    "yaw_tol": {"description": "Yaw tolerance in degrees.", "type": "number", "exclusiveMinimum": 0, "default": 10},
}
"""The tolerances of a planar pose match (this word's and `at_start_of`'s)."""

SCHEMA = {
    "description": "The object's frame matches a target frame within tolerances.",
    "type": "object",
    "additionalProperties": False,
    "required": ["object", "target"],
    "properties": {
        "object": {"description": "Object (or object/frame annotation).", "$ref": OBJREF},
        "target": {"description": "Target object, frame annotation or region.", "$ref": OBJREF},
        **TOLERANCES,
    },
}


@dataclass(frozen=True)
class Aligned:
    a: int
    target: int
    pos_tol: float
    yaw_tol: float


def tolerances(arg: dict) -> tuple[float, float]:
    """(pos_tol, yaw_tol) of a pose-match argument, defaults filled in."""
    return tuple(float(arg.get(k, TOLERANCES[k]["default"])) for k in ("pos_tol", "yaw_tol"))


def compile_aligned(ctx, arg, ref, bound) -> Aligned:
    return Aligned(ctx.frame(ref(arg["object"])), ctx.frame(ref(arg["target"])), *tolerances(arg))


def evaluate_aligned(ev, node: Aligned):
    return P.aligned(ev.xp, ev.frame(node.a), ev.frame(node.target), node.pos_tol, node.yaw_tol)


register(PredicateWord("aligned", SCHEMA, compile_aligned, Aligned, evaluate_aligned))
