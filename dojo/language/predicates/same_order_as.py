"""same_order_as({pairs, into}): the robot's objects went `into` the container in the order the demonstrator moved
their partners (imitate_sorting_sequence). `pairs` lists [demonstrator's object, robot's object]; the order is the
demonstrator actor's, drawn per episode, so the word compiles, against the plan, into `ordered` over
`inside(robot's object, into)` in that order (first times kept in memory, like `ordered`)."""

from __future__ import annotations

from dojo.backends.program_types import ProgramError

from dojo.language.predicate_registry import OBJREF, PredicateWord, register
from dojo.language.predicates.ordered import Ordered

SCHEMA = {
    "description": "The robot's objects went into `into` in the order the demonstrator put their partners in, e.g. "
                   "{pairs: [[demo_lemon, lemon], [demo_can, can]], into: basket/inside}.",
    "type": "object",
    "additionalProperties": False,
    "required": ["pairs", "into"],
    "properties": {
        "pairs": {"description": "[demonstrator's object, robot's object] pairs.", "type": "array", "minItems": 2,
                  "items": {"type": "array", "prefixItems": [{"$ref": OBJREF}, {"$ref": OBJREF}], "items": False,
                            "minItems": 2}},
        "into": {"description": "The container's placement annotation (container/inside) or a region.",
                 "$ref": OBJREF},
    },
}


def demonstrated_order(plan, shown: list[str]) -> list[str]:
    """The order in which the plan's demonstrator moves the objects `shown` (its drawn sequence)."""
    for actor in plan.program.get("actors", []):
        spec = actor.get("demonstrator")
        if spec is not None and set(shown) <= set(spec["objects"]):
            return [n for n in spec["objects"] if n in shown]
    raise ValueError(f"no demonstrator of the task moves {', '.join(shown)}")


def compile_same_order_as(ctx, arg, ref, bound) -> Ordered:
    partner = {ref(d): ref(r) for d, r in arg["pairs"]}
    try:
        order = demonstrated_order(ctx.plan, list(partner))
    except ValueError as err:
        raise ProgramError(f"same_order_as: {err}") from None
    children = tuple(ctx.node({"inside": [partner[d], ref(arg["into"])]}, bound) for d in order)
    return Ordered(children, ctx.order_slots(len(children)))


register(PredicateWord("same_order_as", SCHEMA, compile_same_order_as))
