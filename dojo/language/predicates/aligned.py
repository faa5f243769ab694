"""aligned(object, target): a planar pose match within a position and a yaw tolerance."""

from __future__ import annotations

from dataclasses import dataclass

from dojo.backends import predicates as P

from dojo.language.predicate_registry import OBJREF, PredicateWord, register

SCHEMA = {
    "description": "The object's frame matches a target frame within tolerances.",
    "type": "object",
    "additionalProperties": False,
    "required": ["object", "target"],
    "properties": {
        "object": {"description": "Object (or object/frame annotation).", "$ref": OBJREF},
        "target": {"description": "Target object, frame annotation or region.", "$ref": OBJREF},
        "pos_tol": {"description": "Position tolerance in metres.", "type": "number", "exclusiveMinimum": 0,
                    "default": 0.02},
        "yaw_tol": {"description": "Yaw tolerance in degrees.", "type": "number", "exclusiveMinimum": 0,
                    "default": 10},
    },
}


@dataclass(frozen=True)
class Aligned:
    a: int
    target: int
    pos_tol: float
    yaw_tol: float


def compile_aligned(ctx, arg, ref, bound) -> Aligned:
    return Aligned(ctx.frame(ref(arg["object"])), ctx.frame(ref(arg["target"])),
                   float(arg.get("pos_tol", 0.02)), float(arg.get("yaw_tol", 10.0)))


def evaluate_aligned(ev, node: Aligned):
    return P.aligned(ev.xp, ev.frame(node.a), ev.frame(node.target), node.pos_tol, node.yaw_tol)


register(PredicateWord("aligned", SCHEMA, compile_aligned, Aligned, evaluate_aligned))
