"""The choices a task's actors make, drawn per episode: a conveyor's item order and speed, an opponent's order.

Drawn here, at compile time, from a stream of their own seeded by (task, setting, seed), so they are part of the
plan (`plan.program["actors"]`, every choice resolved) and covered by its hash like the scene (which the same
inputs determine); a replay is exact, and adding an actor to a task does not move its objects.
"""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np


def actor_rng(task_id: str, setting: str, seed: int) -> np.random.Generator:
    """The actors' random stream of one episode (PCG64 from a hash, like the scene's, but a different one)."""
    digest = hashlib.sha256(f"robodojo-actors|{task_id}|{setting}|{seed}".encode()).digest()
    return np.random.Generator(np.random.PCG64(int.from_bytes(digest[:16], "little")))


def draw_actors(actors: list[dict[str, Any]], task_id: str, setting: str, seed: int) -> list[dict[str, Any]]:
    """Each actor with its choices made: `{name: {...}}` as in the spec, ranges and shuffled groups resolved."""
    rng = actor_rng(task_id, setting, seed)
    out = []
    for actor in actors:
        (name, spec), = actor.items()
        out.append({name: DRAWS.get(name, _as_given)(spec, rng)})
    return out


def _as_given(spec: dict[str, Any], rng: np.random.Generator) -> dict[str, Any]:
    return dict(spec)


def _sequence(entries: list[Any], rng: np.random.Generator) -> list[Any]:
    """A sequence with each list inside it replaced by its members in a random order."""
    out: list[Any] = []
    for entry in entries:
        if isinstance(entry, list):
            out += [entry[int(k)] for k in rng.permutation(len(entry))]
        else:
            out.append(entry)
    return out


def _conveyor(spec: dict[str, Any], rng: np.random.Generator) -> dict[str, Any]:
    """Items in their order (a group written as a list comes in a random order) and a speed from its range."""
    items = _sequence(spec["items"], rng)
    speed = spec["speed"]
    if isinstance(speed, list):
        speed = float(rng.uniform(speed[0], speed[1]))
    return {**spec, "items": items, "speed": float(speed)}


def _opponent(spec: dict[str, Any], rng: np.random.Generator) -> dict[str, Any]:
    """Its preference order over the cells (where no line decides, it takes the first free one): drawn for the
    `random` rule, else the spec's fixed `prefer` (default: the cells as listed)."""
    cells = list(spec["cells"])
    if spec.get("rule", "random") == "random":
        return {**spec, "order": [cells[int(k)] for k in rng.permutation(len(cells))]}
    return {**spec, "order": list(spec.get("prefer", cells))}


def _demonstrator(spec: dict[str, Any], rng: np.random.Generator) -> dict[str, Any]:
    """The objects in the order it moves them."""
    return {**spec, "objects": _sequence(spec["objects"], rng)}


DRAWS = {"conveyor": _conveyor, "opponent": _opponent, "demonstrator": _demonstrator}
"""Per actor name, how its choices are drawn (actors without choices are taken as written)."""
