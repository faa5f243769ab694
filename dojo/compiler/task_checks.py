"""Checks of a task spec that a JSON Schema cannot express: names used in one place must be defined in another.

A predicate that names an object the scene does not have would otherwise only fail when the plan is compiled,
or worse, evaluate to a constant: these checks make it a located error at `dojo validate` time.
"""

from __future__ import annotations

import string
from dojo.language import predicates as predicate_words

from dojo.compiler.spec_errors import JsonPath, did_you_mean

Problem = tuple[JsonPath, str, bool]  # (path, message, points at the key rather than the value)

BUILTIN_NAMES = {"table"}


def _defined_names(task: dict) -> tuple[set[str], set[str], set[str]]:
    scene = task["scene"]
    objects: set[str] = set()
    groups: set[str] = set()
    for entry in scene.get("fixtures", []) + scene["objects"]:
        objects.add(entry["name"])
        count = entry.get("count", 1)
        if count > 1:
            objects.update(f"{entry['name']}_{i}" for i in range(count))
        if "group" in entry:
            groups.add(entry["group"])
    regions = set(scene.get("regions", {}))
    return objects, groups, regions


def task_problems(task: dict) -> list[Problem]:
    """Every undefined or duplicated name in a (schema-valid) task spec."""
    problems: list[Problem] = []
    objects, groups, regions = _defined_names(task)
    scene = task["scene"]

    seen: set[str] = set()
    lying: set[str] = set()
    for section in ("fixtures", "objects"):
        for i, entry in enumerate(scene.get(section, [])):
            name = entry["name"]
            if name in seen:
                problems.append((("scene", section, i, "name"), f"duplicate object name '{name}'", False))
            seen.add(name)
            if "region" in entry and entry["region"] not in regions:
                problems.append((("scene", section, i, "region"),
                                 f"unknown region '{entry['region']}'{did_you_mean(entry['region'], regions)}", False))
            if "like" in entry and entry["like"] not in seen - {name}:
                problems.append((("scene", section, i, "like"), f"'like' names '{entry['like']}', which is not an "
                                 f"object listed before this one{did_you_mean(entry['like'], seen)}", False))
            if "color_of" in entry and entry["color_of"] not in seen - {name}:
                problems.append((("scene", section, i, "color_of"), f"'color_of' names '{entry['color_of']}', which "
                                 f"is not an object listed before this one{did_you_mean(entry['color_of'], seen)}",
                                 False))
            if "region" not in entry and "pos" not in entry and "inside" not in entry:
                problems.append((("scene", section, i), f"object '{name}' needs a region, a pos or inside", False))
            if "inside" in entry and entry["inside"] not in seen - {name}:
                problems.append((("scene", section, i, "inside"), f"'inside' names '{entry['inside']}', which is not "
                                 f"an object listed before this one{did_you_mean(entry['inside'], seen)}", False))
            elif "inside" in entry and entry["inside"] in lying:  # its `inside` box would lie on its side too
                problems.append((("scene", section, i, "inside"), f"'inside' names '{entry['inside']}', which lies on "
                                 "its side (rest: side): contents go into an upright container", False))
            if entry.get("rest") == "side":
                lying.add(name)
    for name, region in scene.get("regions", {}).items():
        if "on" in region and region["on"] not in objects:
            problems.append((("scene", "regions", name, "on"),
                             f"unknown fixture '{region['on']}'{did_you_mean(region['on'], objects)}", False))
    if "clutter_region" in scene and scene["clutter_region"] not in regions:
        problems.append((("scene", "clutter_region"), f"unknown region '{scene['clutter_region']}'"
                                                      f"{did_you_mean(scene['clutter_region'], regions)}", False))

    stage_names: set[str] = set()
    for i, stage in enumerate(task.get("stages", [])):
        if stage["name"] in stage_names:
            problems.append((("stages", i, "name"), f"duplicate stage name '{stage['name']}'", False))
        stage_names.add(stage["name"])

    placeable = objects | regions | BUILTIN_NAMES
    predicates: list[tuple[JsonPath, dict]] = [(("success",), task["success"])]
    predicates += [(("stages", i, "when"), s["when"]) for i, s in enumerate(task.get("stages", []))]
    predicates += [(("events", i, "when"), e["when"]) for i, e in enumerate(task.get("events", [])) if "when" in e]
    problems += _event_problems(task.get("events", []), objects)
    problems += _actor_problems(task.get("actors", []), {e["name"] for e in scene["objects"]}, regions, objects,
                                groups)
    for path, pred in predicates:
        (op, arg), = pred.items()
        for ref_path, name, role, quantified in predicate_words.references(op, arg, path, False):
            if role == "group":
                if name not in groups:
                    problems.append((ref_path, f"unknown group '{name}'{did_you_mean(name, groups)}", False))
                continue
            base = name.split("/", 1)[0]
            if base == "_":
                if not quantified:
                    problems.append((ref_path, "'_' stands for the quantified object: use it inside forall/exists",
                                     False))
            elif base not in placeable:
                problems.append((ref_path, f"unknown object or region '{base}'{did_you_mean(base, placeable)}", False))

    for slot, spec in task.get("slots", {}).items():
        if "object" in spec and spec["object"] not in objects:
            problems.append((("slots", slot, "object"),
                             f"unknown object '{spec['object']}'{did_you_mean(spec['object'], objects)}", False))
        if "object" not in spec and "choices" not in spec:
            problems.append((("slots", slot), f"slot '{slot}' needs an object or choices", True))
    placeholders = _placeholders(task["instruction"])
    if placeholders is None:
        problems.append((("instruction",), "unbalanced '{' or '}' (write {slot} for a placeholder)", False))
    for slot in placeholders or []:
        if slot not in task.get("slots", {}):
            problems.append((("instruction",), f"placeholder '{{{slot}}}' has no entry in slots", False))

    for i, step in enumerate(task.get("expert", [])):
        for key in ("object", "target"):
            name = step.get(key)
            if name is not None and name.split("/", 1)[0] not in placeable | {"_"}:
                base = name.split("/", 1)[0]
                problems.append((("expert", i, key),
                                 f"unknown object or region '{base}'{did_you_mean(base, placeable)}", False))
        if "for_each" in step and step["for_each"] not in groups:
            problems.append((("expert", i, "for_each"),
                             f"unknown group '{step['for_each']}'{did_you_mean(step['for_each'], groups)}", False))
    for i, entry in enumerate(scene["objects"]):
        if "hidden_after" in entry and entry["hidden_after"] not in stage_names:
            problems.append((("scene", "objects", i, "hidden_after"), f"unknown stage '{entry['hidden_after']}'"
                                                                      f"{did_you_mean(entry['hidden_after'], stage_names)}", False))
    return problems


def _event_problems(events: list[dict], objects: set[str]) -> list[Problem]:
    """Every name an event acts on that is not an object of the scene (joints are checked when a plan is built)."""
    problems: list[Problem] = []
    for i, event in enumerate(events):
        for action, value in event.items():
            if action in ("at_step", "when"):
                continue
            names = value if isinstance(value, list) else [value]
            for k, name in enumerate(names):
                base = str(name).split("/", 1)[0]
                if base not in objects:
                    path = ("events", i, action) + ((k,) if isinstance(value, list) else ())
                    problems.append((path, f"unknown object '{base}'{did_you_mean(base, objects)}", False))
    return problems


def _actor_problems(actors: list[dict], movable: set[str], regions: set[str], objects: set[str],
                    groups: set[str]) -> list[Problem]:
    """A conveyor's belt must be a region and its items movable objects (not fixtures); an opponent's board an
    object, its pieces groups and the cells of its lines and preference among its cells; a demonstrator's objects
    movable and its arm's parts objects of the scene."""
    problems: list[Problem] = []
    for i, actor in enumerate(actors):
        opponent = actor.get("opponent")
        if opponent is not None:
            for key in ("pieces", "after"):
                if opponent[key] not in groups:
                    problems.append((("actors", i, "opponent", key), f"unknown group '{opponent[key]}'"
                                                                     f"{did_you_mean(opponent[key], groups)}", False))
            if opponent["board"] not in objects:
                problems.append((("actors", i, "opponent", "board"), f"unknown object '{opponent['board']}'"
                                                                     f"{did_you_mean(opponent['board'], objects)}", False))
            cells = set(opponent["cells"])
            named = [(("lines", k, j), c) for k, line in enumerate(opponent.get("lines", []))
                     for j, c in enumerate(line)]
            named += [(("prefer", k), c) for k, c in enumerate(opponent.get("prefer", []))]
            for where, cell in named:
                if cell not in cells:
                    problems.append((("actors", i, "opponent", *where),
                                     f"'{cell}' is not one of the opponent's cells{did_you_mean(cell, cells)}", False))
        for part, name in actor.get("demonstrator", {}).get("arm", {}).items():
            if name not in objects:
                problems.append((("actors", i, "demonstrator", "arm", part),
                                 f"unknown object '{name}'{did_you_mean(name, objects)}", False))
        into = str(actor.get("demonstrator", {}).get("into", "")).split("/", 1)[0]
        if into and into not in objects:
            problems.append((("actors", i, "demonstrator", "into"),
                             f"unknown object '{into}'{did_you_mean(into, objects)}", False))
        shown = actor.get("demonstrator", {}).get("objects", [])
        for k, entry in enumerate(shown):
            for j, name in enumerate(entry if isinstance(entry, list) else [entry]):
                if name not in movable:
                    path = ("actors", i, "demonstrator", "objects", k) + ((j,) if isinstance(entry, list) else ())
                    problems.append((path, f"'{name}' is not a movable object of the scene{did_you_mean(name, movable)}",
                                     False))
        spec = actor.get("conveyor")
        if spec is None:
            continue
        if spec["belt"] not in regions:
            problems.append((("actors", i, "conveyor", "belt"),
                             f"unknown region '{spec['belt']}'{did_you_mean(spec['belt'], regions)}", False))
        for k, entry in enumerate(spec["items"]):
            for j, name in enumerate(entry if isinstance(entry, list) else [entry]):
                if isinstance(name, str) and name not in movable:  # (a number is a pause)
                    path = ("actors", i, "conveyor", "items", k) + ((j,) if isinstance(entry, list) else ())
                    problems.append((path, f"'{name}' is not a movable object of the scene (a conveyor carries "
                                           f"objects, not fixtures){did_you_mean(name, movable)}", False))
    return problems


def _placeholders(text: str) -> list[str] | None:
    """The `{slot}` names of an instruction, or None when its braces are unbalanced."""
    try:
        return [name for _, name, _, _ in string.Formatter().parse(text) if name is not None]
    except ValueError:
        return None
