"""The data a compiled predicate program is made of: its layout (node tree and stages), where its state lives, and
its per-plan parameters. Shared by the program compiler (`predicate_program`), its JSON form in plans
(`program_json`) and the backends that evaluate it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from dojo.backends.predicate_state import StateIndex

Array = Any
Node = Any
"""A compiled predicate: a frozen dataclass defined by its word's module in `dojo.language.predicates`."""


@dataclass(frozen=True)
class Press:
    """How a button's presses are detected: its joint's travel (joint >= 0), or robot contact (atoms)."""

    joint: int
    atoms: tuple[tuple[int, ...], tuple[int, ...]] | None


@dataclass(frozen=True)
class ProgramLayout:
    success: Node
    stages: tuple[Node, ...]
    stage_names: tuple[str, ...]
    weights: tuple[float, ...]
    sequential: bool
    presses: tuple[Press, ...]
    n_order: int
    terms: tuple[Node, ...] = ()
    """The success predicate's named conditions: the children of a top-level `all`, else the predicate itself."""
    term_names: tuple[str, ...] = ()
    triggers: tuple[Node, ...] = ()
    """The `when` predicates of the task's events (`dojo.backends.world_events`), in event order."""


@dataclass
class CompiledProgram:
    layout: ProgramLayout
    index: StateIndex
    params: dict[str, np.ndarray] = field(default_factory=dict)


class ProgramOutput(NamedTuple):
    """One evaluation, batched over N: success bool[N], score float[N] (0-100), stage_step int[N, S]
    (first control step each stage was reached, -1 = not yet), terms bool[N, T] (each success term now, so a
    failed episode says which condition failed), triggers bool[N, E] (each event's `when` now; the backend fires
    an event the first step it holds). A NamedTuple, hence a JAX pytree."""

    success: Array
    score: Array
    stage_step: Array
    terms: Array
    triggers: Array = None


class ProgramError(ValueError):
    """A name in the plan's program does not resolve against the plan and its model. `path` is the spec path of
    the predicate it is in, when known (the compiler turns it into a located spec error)."""

    path: tuple = ()
