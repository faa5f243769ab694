"""The predicate registry: one home per word. A word added in this one file is accepted by the task schema,
checked for its references like a built-in, and compiles and evaluates against a real plan."""

from __future__ import annotations

import copy
import dataclasses
import json
from dataclasses import dataclass

import numpy as np
import pytest
from dojo.backends import predicates as P
from dojo.backends.predicate_program import compile_program
from dojo.compiler.spec_schema import schema_dir, validator_for
from dojo.compiler.task_checks import task_problems
from dojo.language import predicates as words

from test_program import evaluate, state_after


@dataclass(frozen=True)
class Above:
    a: int
    b: int
    margin: float


def compile_above(ctx, arg, ref, bound) -> Above:
    return Above(ctx.frame(ref(arg[0])), ctx.frame(ref(arg[1])), float(arg[2]))


def evaluate_above(ev, node: Above):
    za = P.box_center(ev.xp, *ev.frame(node.a)[:3])[:, 2]
    zb = P.box_center(ev.xp, *ev.frame(node.b)[:3])[:, 2]
    return za - zb >= node.margin


ABOVE = words.PredicateWord(
    "above",
    {"description": "[a, b, margin]: a's centre is at least margin metres higher than b's.", "type": "array",
     "prefixItems": [{"$ref": words.OBJREF}, {"$ref": words.OBJREF}, {"type": "number"}], "items": False,
     "minItems": 3},
    compile_above, Above, evaluate_above)


@pytest.fixture
def above():
    words.register(ABOVE)
    yield ABOVE
    words.unregister("above")


def test_the_schema_file_lists_exactly_the_registered_words():
    schema = json.loads((schema_dir() / "task.schema.json").read_text())
    assert schema["$defs"]["predicate"]["properties"] == words.schema_properties(), \
        "specs/schemas/task.schema.json and dojo.language.predicates disagree: update the file from the registry"


def test_every_word_compiles_or_is_sugar_and_every_node_is_evaluated():
    for name in words.names():
        word = words.word(name)
        assert callable(word.compile)
        if word.node is not None:
            assert words.evaluator(word.node) is word.evaluate


def test_a_word_cannot_be_defined_twice():
    with pytest.raises(ValueError, match="already defined"):
        words.register(dataclasses.replace(words.word("on")))


def test_a_new_word_is_accepted_by_the_schema_only_while_registered(library, above):
    task = copy.deepcopy(library.get("task", "probe_predicates").data)
    task["success"] = {"all": [{"above": ["cube_0", "bin", 0.05]}, {"on": ["cube_1", "table"]}]}
    assert list(validator_for("task").iter_errors(task)) == []
    bad = copy.deepcopy(task)
    bad["success"] = {"above": ["cube_0", "bin"]}  # margin missing
    assert list(validator_for("task").iter_errors(bad))
    words.unregister("above")
    try:
        assert list(validator_for("task").iter_errors(task))  # unknown predicate again
    finally:
        words.register(ABOVE)


def test_a_new_word_gets_the_reference_checks_from_its_schema(library, above):
    task = copy.deepcopy(library.get("task", "probe_predicates").data)
    task["success"] = {"forall": {"group": "cubes", "holds": {"above": ["_", "ghost", 0.01]}}}
    messages = [message for _, message, _ in task_problems(task)]
    assert any("unknown object or region 'ghost'" in m for m in messages), messages
    task["success"] = {"above": ["_", "bin", 0.01]}
    assert any("'_' stands for the quantified object" in m for _, m, _ in task_problems(task))


def test_a_new_word_compiles_and_evaluates_on_a_real_plan(probe_plan, set_free_pose, above):
    plan = dataclasses.replace(probe_plan, program={"success": {"above": ["cube_0", "bin", 0.1]}, "stages": []},
                               compiled_program={})
    program = compile_program(plan, probe_plan.model())
    qpos = np.asarray(probe_plan.init_qpos)
    assert evaluate(plan, program, state_after(probe_plan, qpos)).success.tolist() == [False]
    bin_pos = probe_plan.initial_data().xpos[probe_plan.model().body("bin").id]
    set_free_pose(probe_plan, qpos, "cube_0", bin_pos + [0.0, 0.0, 0.3])
    assert evaluate(plan, program, state_after(probe_plan, qpos)).success.tolist() == [True]
