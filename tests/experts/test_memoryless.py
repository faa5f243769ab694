"""The memory check's memoryless expert: what each Memory task declares forgotten is guessed (facts, confused
objects, orders, step order, start poses), deterministically per episode, and the chance level is the probability
that every guess is right."""

from __future__ import annotations

import pytest
from dojo.compiler.plan import compile_plan
from dojo.compiler.spec_library import SpecLibrary
from dojo.experts.memoryless import chance_level, forgetful
from dojo.experts.validity import runs


@pytest.fixture(scope="module")
def lib() -> SpecLibrary:
    return SpecLibrary.load(strict=False)


MEMORY_TASKS = {"cover_blocks": 1 / 6, "swap_blocks": 1 / 120, "press_by_number": 1 / 9, "swap_t": 0.0,
                "match_and_pick_from_conveyor": 1 / 3, "imitate_sorting_sequence": 1 / 120}


def test_every_memory_task_declares_its_history_and_has_a_chance_level(lib):
    memory = sorted(s.id for s in lib.of_kind("task")
                    if s.data["dimension"] == "memory" and "real_world" not in s.data.get("tags", []))
    assert memory == sorted(MEMORY_TASKS)
    for task, chance in MEMORY_TASKS.items():
        spec = lib.get("task", task)
        assert runs("memoryless", spec) and chance_level(lib, spec) == pytest.approx(chance)
    assert not runs("memoryless", lib.get("task", "stack_blocks"))


def test_guesses_repeat_per_episode_and_vary_across_episodes(lib):
    spec = lib.get("task", "press_by_number")
    guesses = set()
    for seed in range(6):
        plan = compile_plan(lib, spec, "standard", seed)
        believed, steps = forgetful(lib, spec, plan, spec.data["expert"])
        again = forgetful(lib, spec, plan, spec.data["expert"])[1]
        assert steps == again and believed.hash == plan.hash
        guesses.add((steps[0]["times"], steps[1]["times"]))
        assert {steps[0]["times"], steps[1]["times"]} <= {1, 2, 3}
    assert len(guesses) > 1


def test_confused_objects_and_shuffled_steps(lib):
    match = lib.get("task", "match_and_pick_from_conveyor")
    caught = set()
    for seed in range(8):
        plan = compile_plan(lib, match, "standard", seed)
        caught.add(forgetful(lib, match, plan, match.data["expert"])[1][0]["object"])
    assert caught == {"match", "other_a", "other_b"}
    swap = lib.get("task", "swap_blocks")
    plan = compile_plan(lib, swap, "standard", 0)
    steps = forgetful(lib, swap, plan, swap.data["expert"])[1]
    assert sorted(map(str, steps[:6])) == sorted(map(str, swap.data["expert"][:6])) and steps[6:] == swap.data["expert"][6:]
