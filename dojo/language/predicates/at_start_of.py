"""at_start_of(object, of): the object lies where `of` lay when the episode started, in the ground plane and in
heading, within tolerances. The start pose is kept with the plan, so it holds after `of` has moved away: the
memory task swap_T asks each T to take the other's start pose, which no image shows any more."""

from __future__ import annotations

from dataclasses import dataclass

from dojo.backends import predicates as P

from dojo.language.predicate_registry import OBJREF, PredicateWord, register
from dojo.language.predicates.aligned import TOLERANCES, tolerances

SCHEMA = {
    "description": "The object's frame matches the frame `of` had at the start of the episode (reference points "
                   "within pos_tol in the ground plane, headings within yaw_tol degrees), e.g. {object: t_red/center,"
                   " of: t_green/center}.",
    "type": "object",
    "additionalProperties": False,
    "required": ["object", "of"],
    "properties": {
        "object": {"description": "Object (or object/frame annotation).", "$ref": OBJREF},
        "of": {"description": "Object (or object/frame annotation) whose start pose is the target.", "$ref": OBJREF},
        **TOLERANCES,
    },
}


@dataclass(frozen=True)
class AtStartOf:
    a: int
    start: int
    """Frame slot whose start pose (`params["init_center"]`, `params["init_mat"]`) is the target."""
    pos_tol: float
    yaw_tol: float


def compile_at_start_of(ctx, arg, ref, bound) -> AtStartOf:
    return AtStartOf(ctx.frame(ref(arg["object"])), ctx.start_pose(ref(arg["of"])), *tolerances(arg))


def evaluate_at_start_of(ev, node: AtStartOf):
    xp = ev.xp
    centre = ev.params["init_center"][:, node.start]
    start = (centre, ev.params["init_mat"][:, node.start], xp.zeros_like(centre), xp.zeros_like(centre))
    return P.aligned(xp, ev.frame(node.a), start, node.pos_tol, node.yaw_tol)


register(PredicateWord("at_start_of", SCHEMA, compile_at_start_of, AtStartOf, evaluate_at_start_of))
