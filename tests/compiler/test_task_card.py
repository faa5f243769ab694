"""Task cards: generated from the spec alone, every part of the task stated, words described from the registry."""

from __future__ import annotations

from pathlib import Path

from dojo.compiler.spec_library import SpecLibrary
from dojo.compiler.task_card import task_card
from dojo.language.predicates import render

PACK = Path(__file__).parents[1] / "specs" / "pack"


def test_predicates_render_as_calls_with_children_in_place():
    pred = {"all": [{"forall": {"group": "cubes", "holds": {"inside": ["_", "bin"]}}}, {"pressed": ["button", 2]},
                    {"aligned": {"object": "t", "target": "goal", "pos_tol": 0.01}}]}
    assert render(pred) == ("all(forall(group=cubes, holds=inside(_, bin)), pressed(button, 2), "
                                      "aligned(object=t, target=goal, pos_tol=0.01))")


def test_the_card_states_the_task():
    library = SpecLibrary.load([PACK])
    card = task_card(library.get("task", "stack_test"), "Put the red block on the plate.", {"head": "x_head.png"})
    for text in ("# stack_test (`stack_test`)", "**Dimension** generalization", "> Put the {color} block",
                 "This episode: *Put the red block on the plate.*", "`{color}`: the color of `block`",
                 "- `block`: any asset with category test_block, in region `left`, colour red",
                 "Success: `on(block, plate)`", "| placed | `on(block, plate)` | 2 |",
                 "- `lifted`: [a, height]: a is at least height metres above its initial height.",
                 "![head](x_head.png)"):
        assert text in card, text
