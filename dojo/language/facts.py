"""Facts of a scene: values a task spec refers to but the sampler decides, such as the number on a card drawn for
this episode (`{attribute: [card_left, number]}`).

A fact is written where a predicate or an expert step takes a plain value. The compiler replaces each with its
value for the episode when it builds the plan (`resolve_facts` over the plan's objects), so the resolved program,
the plan hash's inputs and a replay agree, and a backend never sees a fact. The scripted expert resolves its own
steps the same way: it may know what the robot was shown, never more.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

FACT = "#/$defs/fact"
SCHEMA: dict[str, Any] = {
    "description": "A value of this episode's scene: `{attribute: [object, key]}` is the object's attribute `key` "
                   "(its asset's `attributes`, its entry's `attributes`, `name` or `color`), e.g. "
                   "{attribute: [card_left, number]} for the number of the card drawn for the episode.",
    "type": "object",
    "additionalProperties": False,
    "required": ["attribute"],
    "properties": {"attribute": {"description": "[object, key]: the object and the name of its attribute.",
                                 "type": "array", "prefixItems": [{"$ref": "#/$defs/objref"}, {"type": "string"}],
                                 "items": False, "minItems": 2}},
}


class FactError(ValueError):
    """A fact names an object or attribute the episode's scene does not have; `path` is where, in the value."""

    def __init__(self, message: str, path: tuple) -> None:
        super().__init__(message)
        self.path = path


def is_fact(value: Any) -> bool:
    return isinstance(value, dict) and set(value) == {"attribute"} and isinstance(value["attribute"], list)


def resolve_facts(value: Any, objects: Mapping[str, Mapping[str, Any]], path: tuple = ()) -> Any:
    """`value` (a predicate, an event, an expert step, ...) with every fact replaced by its value among `objects`
    (name -> {"attributes": {...}}, as a plan holds them)."""
    if is_fact(value):
        name, key = value["attribute"]
        if name not in objects:
            raise FactError(f"fact {value}: the scene has no object {name!r}", path)
        attributes = objects[name].get("attributes") or {}
        if key not in attributes:
            raise FactError(f"fact {value}: object {name!r} has no attribute {key!r} (it has: "
                            f"{', '.join(sorted(attributes)) or 'none'})", path)
        return attributes[key]
    if isinstance(value, dict):
        return {k: resolve_facts(v, objects, path + (k,)) for k, v in value.items()}
    if isinstance(value, list):
        return [resolve_facts(v, objects, path + (i,)) for i, v in enumerate(value)]
    return value
