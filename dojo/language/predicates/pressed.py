"""pressed(button, times[, exactly]): the button went down at least `times` times since the episode started, or
exactly `times` times with `exactly` (a count kept in the program's memory, so it survives the button coming
back up; a count that overshot never comes back down, so `exactly` fails for good once it is passed)."""

from __future__ import annotations

from dataclasses import dataclass

from dojo.language.facts import FACT
from dojo.language.predicate_registry import OBJREF, PredicateWord, register

EXACTLY = "exactly"
SCHEMA = {
    "description": "[button, times] or [button, times, exactly]: the button was pressed at least times times "
                   "(exactly times times with `exactly`). times may be a fact of the scene, "
                   "{attribute: [card, number]}: press_by_number presses as often as a drawn card says.",
    "type": "array",
    "prefixItems": [{"$ref": OBJREF}, {"oneOf": [{"type": "integer", "minimum": 1}, {"$ref": FACT}]},
                    {"enum": [EXACTLY]}],
    "items": False,
    "minItems": 2,
}


@dataclass(frozen=True)
class Pressed:
    press: int
    times: int
    exact: bool = False


def compile_pressed(ctx, arg, ref, bound) -> Pressed:
    return Pressed(ctx.press(ref(arg[0])), int(arg[1]), len(arg) > 2 and arg[2] == EXACTLY)


def evaluate_pressed(ev, node: Pressed):
    count = ev.press_count[:, node.press]
    return count == node.times if node.exact else count >= node.times


register(PredicateWord("pressed", SCHEMA, compile_pressed, Pressed, evaluate_pressed))
