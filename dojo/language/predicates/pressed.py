"""pressed(button, times): the button went down at least `times` times since the episode started (a count kept
in the program's memory, so it survives the button coming back up)."""

from __future__ import annotations

from dataclasses import dataclass

from dojo.language.predicate_registry import OBJREF, PredicateWord, register

SCHEMA = {
    "description": "[button, times]: the button was pressed at least times times.",
    "type": "array",
    "prefixItems": [{"$ref": OBJREF}, {"type": "integer", "minimum": 1}],
    "items": False,
    "minItems": 2,
}


@dataclass(frozen=True)
class Pressed:
    press: int
    times: int


def compile_pressed(ctx, arg, ref, bound) -> Pressed:
    return Pressed(ctx.press(ref(arg[0])), int(arg[1]))


def evaluate_pressed(ev, node: Pressed):
    return ev.press_count[:, node.press] >= node.times


register(PredicateWord("pressed", SCHEMA, compile_pressed, Pressed, evaluate_pressed))
