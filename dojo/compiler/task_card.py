"""A task card: one Markdown page that says what a task is, generated from its spec (`dojo show task=...`).

A reviewer of a contributed task, or a researcher reading results, should not have to read YAML: the card gives
the instruction, the scene, the settings, success and score stages written as predicates, the words used with
what each means (their schema descriptions, so a new word is described without code here), the expert's
skills and the horizon, and links the rendered camera images beside it.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from dojo.language import predicates as predicate_words
from dojo.language import skills as skill_words

from dojo.compiler.spec_library import Spec


def _words_in(pred: Any) -> Iterator[str]:
    if isinstance(pred, dict):
        for key, value in pred.items():
            if predicate_words.word(key) is not None:
                yield key
            yield from _words_in(value)
    elif isinstance(pred, list):
        for item in pred:
            yield from _words_in(item)


def _object_line(entry: dict[str, Any]) -> str:
    asset = entry["asset"]
    asset_text = asset if isinstance(asset, str) else "any asset with " + ", ".join(f"{k} {v}" for k, v in
                                                                                    asset.items())
    if "draw_from" in entry:
        asset_text = "one of " + ", ".join(str(a) for a in entry["draw_from"]) + " drawn per episode"
    where = f"in region `{entry['region']}`" if "region" in entry else f"at {entry.get('pos')}"
    extras = [f"x{entry['count']}" if entry.get("count", 1) > 1 else "",
              f"group `{entry['group']}`" if "group" in entry else "",
              f"colour {entry['color']}" if "color" in entry else "",
              "lying on its side" if entry.get("rest") == "side" else ""]
    return f"- `{entry['name']}`: {asset_text}, {where}" + "".join(f", {e}" for e in extras if e)


def task_card(task: Spec, instruction: str | None = None, images: dict[str, str] | None = None) -> str:
    """The card of `task`; `instruction` is one sampled instruction, `images` camera name -> image file name."""
    data = task.data
    lines = [f"# {data.get('title', task.id)} (`{task.id}`)", ""]
    lines += [f"**Dimension** {data['dimension']} · **embodiment** {data['embodiment']} · **horizon** "
              f"{data.get('horizon')}" + (f" (fallback {data['horizon_fallback']})" if "horizon_fallback" in data
                                          else ""), ""]
    if data.get("description"):
        lines += [data["description"], ""]
    lines += ["## Instruction", "", f"> {data['instruction']}", ""]
    if instruction and instruction != data["instruction"]:
        lines += [f"This episode: *{instruction}*", ""]
    slots = [f"- `{{{slot}}}`: " + (f"the {spec['attribute']} of `{spec['object']}`" if "object" in spec
                                    else f"one of {', '.join(map(str, spec.get('choices', [])))}")
             for slot, spec in data.get("slots", {}).items()]
    scene = data["scene"]
    lines += [*slots, *([""] if slots else []), "## Scene", ""]
    lines += [_object_line(e) + " (fixture)" for e in scene.get("fixtures", [])]
    lines += [_object_line(e) for e in scene["objects"]]
    for name, region in scene.get("regions", {}).items():
        on = f" on `{region['on']}`" if "on" in region else ""
        lines.append(f"- region `{name}`: {region['size'][0]} x {region['size'][1]} m at {region['center']}{on}")
    lines += ["", "## Settings", ""]
    settings = data.get("settings") or {}
    lines += [f"- **{name}**: " + (", ".join(f"{k} {v}" for k, v in cfg.items()) or "defaults")
              for name, cfg in settings.items()] or ["- `standard` and `random` with the defaults"]
    lines += ["", "## Success and score", "", f"Success: `{predicate_words.render(data['success'])}`, and every stage "
              "reached.", ""]
    stages = data.get("stages", [])
    if stages:
        order = data.get("stage_order", "any")
        lines += [f"Stages ({'in order' if order == 'sequential' else 'in any order'}; score = weighted fraction "
                  "reached):", "", "| stage | when | weight |", "|---|---|---|"]
        lines += [f"| {s['name']} | `{predicate_words.render(s['when'])}` | {s.get('weight', 1)} |" for s in stages]
        lines.append("")
    used = sorted(set(_words_in([data["success"], *[s["when"] for s in stages]])))
    lines += ["Words used:", ""]
    lines += [f"- `{w}`: {predicate_words.word(w).schema.get('description', '')}" for w in used]
    if data.get("expert"):
        lines += ["", "## Scripted expert", ""]
        for i, step in enumerate(data["expert"], 1):
            skill = skill_words.word(step["skill"])
            args = ", ".join(f"{k}={v}" for k, v in step.items() if k != "skill")
            lines.append(f"{i}. `{step['skill']}`({args})" + (f": {skill.description}" if skill else ""))
    if images:
        lines += ["", "## Cameras", ""]
        lines += [f"![{name}]({path})" for name, path in images.items()]
    return "\n".join(lines) + "\n"
