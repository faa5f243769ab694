"""A task's actors (`actors:` in the task spec): built-in behaviours, chosen by name, that act on the world every
control step inside the backend's step, on the simulator state (a policy sees only their effects, in its images).

`compile_actors(plan, model)` builds each actor of `plan.program["actors"]` (its per-episode choices already drawn
by the compiler, `dojo.compiler.actor_draws`) through `BUILDERS`; an actor offers `start(data) -> state` for a
fresh episode and `hold(state, data, step)`, called before every physics step with the control steps done so far.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import mujoco

from dojo.backends.conveyor import Conveyor
from dojo.backends.demonstrator import Demonstrator
from dojo.backends.opponent import Opponent
from dojo.backends.world_events import compile_events


class Actor(Protocol):
    def start(self, data: mujoco.MjData) -> Any: ...

    def hold(self, state: Any, data: mujoco.MjData, step: int) -> None: ...


BUILDERS: dict[str, Callable[[Any, mujoco.MjModel, dict[str, Any]], Actor]] = {
    "conveyor": Conveyor, "opponent": Opponent, "demonstrator": Demonstrator}
"""Actor name (the key in the spec) -> its constructor (plan, model, resolved spec)."""


def compile_actors(plan: Any, model: mujoco.MjModel) -> list[Actor]:
    """The plan's actors, built against its model (empty when the task has none)."""
    out = []
    for actor in plan.program.get("actors", []):
        (name, spec), = actor.items()
        out.append(BUILDERS[name](plan, model, spec))
    return out


def first_state(plan: Any, model: mujoco.MjModel) -> mujoco.MjData:
    """The state a policy sees at an episode's first step: the plan's initial state with the task's events and
    actors started (an item that enters a belt later is not on it yet), for pictures of the task (`dojo show`)."""
    data = plan.initial_data(model)
    events = compile_events(plan, model)
    if events is not None:
        events.start(data)
    for actor in compile_actors(plan, model):
        actor.start(data)
    mujoco.mj_forward(model, data)
    return data
