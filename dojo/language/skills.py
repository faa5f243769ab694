"""The skill registry: every skill word a task's scripted expert (`expert:` in a task spec) may use.

A `SkillWord` names a skill, says what it does (the task schema's `skill` enum and its description are built
from this registry, so the schema and the expert cannot disagree) and says where its runner is: a callable
``run(ctx, step) -> iterator of motion segments``, or a ``"module:function"`` path to one. The built-in runners
live in the scripted expert (`dojo.experts`), which needs MuJoCo and an IK solver; naming them by path
keeps spec validation free of those imports. Paths are written here, in code: a spec only ever names a word.

Adding a skill is one registration: `register(SkillWord("wipe", "...", run_wipe))`.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

from dojo.language.registry import Registry

Runner = Callable[[Any, dict[str, Any]], Iterator[Any]]
_EXPERT = "dojo.experts.skills"
_ARTICULATED = "dojo.experts.articulated"
_PRECISION = "dojo.experts.precision_skills"
_FITS = {"insert", "plug", "screw"}
"""The built-in skills that fit an object into a tight target (`SkillWord.inserts`)."""


@dataclass(frozen=True)
class SkillWord:
    """One skill: its name, a one-line description, and its runner (a callable or a ``module:function`` path)."""

    name: str
    description: str
    run: Runner | str
    inserts: bool = False
    """Whether the skill fits its object into its target (a hole, slot or socket) with little play: the perturbed
    expert (`dojo.experts.perturbed`) aims these targets off by a few millimetres to show that the fit binds."""

    def runner(self) -> Runner:
        """The runner, imported on first use when given as a path."""
        if callable(self.run):
            return self.run
        module, _, attr = self.run.partition(":")
        return getattr(importlib.import_module(module), attr)


_SKILLS: Registry[SkillWord] = Registry("skill")


def register(skill: SkillWord) -> SkillWord:
    """Add a skill word (accepted by the task schema from now on)."""
    return _SKILLS.add(skill.name, skill)


def unregister(name: str) -> None:
    """Remove a skill word (tests that add one take it out again)."""
    _SKILLS.remove(name)


def version() -> int:
    """Changes whenever the set of skills does (validator caches key on it)."""
    return _SKILLS.version


def word(name: str) -> SkillWord | None:
    return _SKILLS.get(name)


def names() -> list[str]:
    """The skill names in registration order (the schema's enum)."""
    return list(_SKILLS.entries())


def schema_property() -> dict[str, Any]:
    """The task schema's `$defs/skill/properties/skill`: the enum of skill names with what each does."""
    lines = "; ".join(f"`{s.name}`: {s.description}" for s in _SKILLS.entries().values())
    return {"description": f"The skill. {lines}", "enum": names()}


for _name, _description, _run in (
    ("grasp", "pick the object from above and lift it clear of the table", f"{_EXPERT}:run_grasp"),
    ("place", "pick the object and put it at the target (handed over when no one arm reaches both)",
     f"{_EXPERT}:run_place"),
    ("handover", "bring the object to the target with the arm that reaches it, the other arm handing it over "
                 "first", f"{_EXPERT}:run_handover"),
    ("insert", "put the object into the target's hole or slot, aligned above it and lowered slowly",
     f"{_EXPERT}:run_insert"),
    ("open", "open an articulated fixture by its handle to `amount` of its range", f"{_ARTICULATED}:run_open"),
    ("close", "close an articulated fixture by its handle", f"{_ARTICULATED}:run_close"),
    ("stack", "put the object on top of the target", f"{_EXPERT}:run_stack"),
    ("push", "bring the object onto the target frame with the target's heading", f"{_EXPERT}:run_push"),
    ("push_up", "lift the object (grasped first if not held) to `height` above the table", f"{_EXPERT}:run_push_up"),
    ("press", "press a button with the closed fingertips, then come back up", f"{_EXPERT}:run_press"),
    ("release", "let go and back out along the approach axis", f"{_EXPERT}:run_release"),
    ("home", "return both arms to their home pose", f"{_EXPERT}:run_home"),
    ("wait", "hold still for `steps` control steps", f"{_EXPERT}:run_wait"),
    ("strike", "hit the target point with the held tool's head, driven down at speed", f"{_PRECISION}:run_strike"),
    ("pour", "tip the container's contents into the target, its mouth held over the target's", f"{_PRECISION}:run_pour"),
    ("plug", "put the object's leading end (`tip`) into the target socket: its heading turned to the socket's, aimed "
             "at the entrance to a fraction of a millimetre, pushed to the floor", "dojo.experts.keyed_skills:run_plug"),
    ("turn", "grip the object where it stands (a key in its lock) and turn it `angle` degrees about the vertical, "
             "counter-clockwise seen from above", "dojo.experts.keyed_skills:run_turn"),
    ("catch", "pick the object off the moving conveyor belt that carries it, fingers open across the belt where it "
              "will pass (then put at the target, if one is given)", "dojo.experts.conveyor_skills:run_catch"),
    ("lift", "raise the object `height` above the table and set it down again where it stood",
     "dojo.experts.lift_skills:run_lift"),
    ("place_free", "put the object on the first free one of the target's `places` (a board game's move)",
     "dojo.experts.board_skills:run_place_free"),
    ("imitate", "once the demonstrator is done, put the robot's partner of each of its objects (`pairs`) at the "
                "target, in the order it moved them", "dojo.experts.imitation_skills:run_imitate"),
    ("screw", "fasten the screw in the thread whose socket is the target: insert it, then turn it `turns` full "
              "turns, a quarter turn per grasp", "dojo.experts.thread_skills:run_screw"),
):
    register(SkillWord(_name, _description, _run, inserts=_name in _FITS))
