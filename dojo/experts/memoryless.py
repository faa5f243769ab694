"""The memory check: the scripted expert denied the history (`memory:` in a task spec), and the chance level it
is held to.

A Memory task says what an agent that acts on the current state only cannot know, in four words a task may use:
- `facts`: facts of the scene ({attribute: [card, number]}) no longer shown; the memoryless expert guesses each,
  uniformly among the values the object's `draw_from` assets carry;
- `confuse`: objects that look alike once the expert has done `after` of its steps (covers over blocks, items on a
  belt); it takes them for one another, by a uniformly random permutation, in every later step;
- `orders`: the order the task's actors chose (what a demonstrator did); it guesses it (drawn again);
- `steps`: [first, end) of the expert's steps whose progress leaves no trace (presses that change nothing in
  view); it does them in a guessed order;
- `start_poses`: where things lay at the start; it guesses (the start of another episode of the task).
Each guess comes from the episode's own stream (`forgetting_rng`), so a run repeats exactly. The chance level is
the probability that every discrete guess is right (`chance_level`): one over the number of equally likely
guesses; a guessed pose or a guessed order over continuous choices is never exactly right, so its chance is 0.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import itertools
import math
from typing import Any

import numpy as np

from dojo.compiler.actor_draws import draw_actors
from dojo.compiler.plan import compile_plan
from dojo.language.facts import resolve_facts

from dojo.experts.oracle import OraclePolicy, ScriptedExpert


def forgetting_rng(plan: Any) -> np.random.Generator:
    """The memoryless expert's guesses for one episode (PCG64 from a hash of the plan)."""
    digest = hashlib.sha256(f"robodojo-memoryless|{plan.hash}".encode()).digest()
    return np.random.Generator(np.random.PCG64(int.from_bytes(digest[:16], "little")))


def fact_values(library: Any, task: Any, fact: dict[str, Any]) -> list[Any]:
    """The values a fact could take: its key over the object's `draw_from` assets (its one asset without)."""
    name, key = fact["attribute"]
    entry = next(e for e in task.data["scene"].get("objects", []) + task.data["scene"].get("fixtures", [])
                 if e["name"] == name)
    refs = entry.get("draw_from", [entry["asset"]])
    return sorted({library.resolve(task, "asset", ref)[0].data.get("attributes", {}).get(key) for ref in refs},
                  key=str)


def _distinct_orders(items: list[Any]) -> int:
    return len({tuple(map(repr, p)) for p in itertools.permutations(items)})


def chance_level(library: Any, task: Any) -> float:
    """The probability that every guess the memoryless expert makes about the task's history is right."""
    memory = task.data.get("memory", {})
    steps = task.data.get("expert", [])
    chance = 1.0
    for fact in memory.get("facts", []):
        chance /= len(fact_values(library, task, fact))
    for group in memory.get("confuse", []):
        later = {v for step in steps[group.get("after", 0):] for v in step.values() if isinstance(v, str)}
        used = sum(1 for name in group["objects"] if name in later)
        chance /= math.perm(len(group["objects"]), used)
    if memory.get("orders"):
        for actor in task.data.get("actors", []):
            (_, spec), = actor.items()
            for entry in spec.get("objects", spec.get("items", [])):
                if isinstance(entry, list):
                    chance /= math.factorial(len(entry))
    if "steps" in memory:
        first, end = memory["steps"]
        chance /= _distinct_orders(steps[first:end])
    if memory.get("start_poses"):
        chance = 0.0
    return chance


def forgetful(library: Any, task: Any, plan: Any, steps: list[dict[str, Any]]) -> tuple[Any, list[dict[str, Any]]]:
    """The plan and expert steps as the memoryless expert believes them: every forgotten thing guessed."""
    memory = task.data.get("memory", {})
    rng = forgetting_rng(plan)
    objects = copy.deepcopy(plan.objects)
    for fact in memory.get("facts", []):
        values = fact_values(library, task, fact)
        name, key = fact["attribute"]
        objects[name]["attributes"][key] = values[int(rng.integers(len(values)))]
    steps = resolve_facts(copy.deepcopy(steps), objects)
    for group in memory.get("confuse", []):
        names = list(group["objects"])
        mapping = dict(zip(names, [names[int(k)] for k in rng.permutation(len(names))]))
        for step in steps[group.get("after", 0):]:
            for key, value in step.items():
                if isinstance(value, str):
                    base, sep, rest = value.partition("/")
                    step[key] = mapping.get(base, base) + sep + rest
    if "steps" in memory:
        first, end = memory["steps"]
        steps[first:end] = [steps[first + int(k)] for k in rng.permutation(end - first)]
    program = dict(plan.program)
    if memory.get("orders"):
        program["actors"] = draw_actors(task.data.get("actors", []), task.id, plan.setting, int(rng.integers(2**31)))
    believed = dataclasses.replace(plan, objects=objects, program=program)
    if memory.get("start_poses"):
        other = compile_plan(library, task, plan.setting, int(rng.integers(10_000, 2**31)))
        believed = dataclasses.replace(believed, init_qpos=other.init_qpos)
    return believed, steps


class MemorylessOracle(OraclePolicy):
    """PRIVILEGED like the oracle, but each episode's expert forgets what its task's `memory:` says a policy acting
    on the current state could not know (`forgetful`)."""

    def new_expert(self, plan: Any) -> ScriptedExpert:
        self.expert_steps(plan.task)  # loads the library
        task = self._library.get("task", plan.task)
        believed, steps = forgetful(self._library, task, plan, list(task.data.get("expert", [])))
        return ScriptedExpert(believed, steps)
