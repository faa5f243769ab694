"""Events of a task (`events:` in the task spec): the world changing by itself, at a control step or when a
predicate first holds. Run by the CPU backend inside its step, on the simulator state; a policy only sees their
effects in its images.

Each event has one trigger, `at_step: k` (fires once the episode has run k control steps) or `when: <predicate>`
(fires the first step the predicate holds: the predicate is compiled into the plan's program as a trigger,
`ProgramLayout.triggers`), and one action:
- `hide: obj` takes a movable object out of the scene (it is parked out of sight and out of reach, held still),
  remembering where it was; `show: obj` puts it back there;
- `spawn: obj`: the object is absent from the start of the episode and appears, when the event fires, where the
  scene sampler placed it;
- `remove: obj`: parked for good;
- `cover: [occluder, target]`: the movable occluder is put over the target (centred on it, at its own start
  height and attitude: a cup upside down over a card);
- `lock: obj/joint` holds the joint where it is (with `at_step: 0`, where it starts, from the first physics step);
  `unlock: obj/joint` frees it again.
Every event fires at most once. Parked objects and locked joints are held by writing their positions and zero
velocities before each control step (locked joints after every physics step too), so nothing else about the model
changes (plans of a task share one model).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

OBJECT_ACTIONS = ("hide", "show", "spawn", "remove")
JOINT_ACTIONS = ("lock", "unlock")
ACTIONS = (*OBJECT_ACTIONS, "cover", *JOINT_ACTIONS)
PARK = np.array([-2.0, -2.5, 0.3])
"""Where the first parked object is held (behind the robot, above the floor, out of every camera's view);
the k-th is PARK_STEP further along x, so parked objects never touch."""
PARK_STEP = 0.4


class EventError(ValueError):
    """An event names something the plan's scene does not have; `path` is its spec path (`events.<i>.<key>`)."""

    def __init__(self, message: str, path: tuple) -> None:
        super().__init__(message)
        self.path = path


@dataclass(frozen=True)
class Event:
    """One compiled event: its trigger (`trigger` >= 0 indexes `ProgramLayout.triggers`, else `at_step`), its action
    and the state addresses it writes (a free joint's 7 qpos and 6 dofs, or one joint's qpos and dof)."""

    action: str
    trigger: int
    at_step: int
    name: str
    qpos: tuple[int, ...]
    dof: tuple[int, ...]
    target: str | None = None


@dataclass
class EventState:
    """One episode's event bookkeeping: which events fired, what is parked (and where it was) and what is locked."""

    fired: set[int] = field(default_factory=set)
    parked: dict[str, np.ndarray] = field(default_factory=dict)
    """Parked object -> the qpos it had when hidden (to `show` it again)."""
    locked: dict[str, float] = field(default_factory=dict)


class WorldEvents:
    """The compiled events of one plan (`compile_events`); per episode state lives in an `EventState`."""

    def __init__(self, plan: Any, model: mujoco.MjModel, events: list[Event]) -> None:
        self.plan, self.model, self.events = plan, model, events
        self.init_qpos = np.asarray(plan.init_qpos, dtype=float)
        movable = sorted({e.name for e in events if e.action in (*OBJECT_ACTIONS, "cover")})
        self.park = {name: PARK + [PARK_STEP * k, 0.0, 0.0] for k, name in enumerate(movable)}
        self._by_name = {e.name: e for e in events}

    def start(self, data: mujoco.MjData) -> EventState:
        """A fresh episode: objects that are spawned later are parked from the first step."""
        state = EventState()
        for k, event in enumerate(self.events):
            if event.action == "spawn" and event.name not in state.parked:
                state.parked[event.name] = self.init_qpos[list(event.qpos)].copy()
            elif event.action == "lock" and event.trigger < 0 and event.at_step == 0:
                # locked from the first physics step, not after the first control step: a lock that holds until a
                # key is in must not give way to whatever pushes it before the first check
                state.fired.add(k)
                state.locked[event.name] = float(self.init_qpos[event.qpos[0]])
        self.hold(state, data)
        return state

    def hold(self, state: EventState, data: mujoco.MjData) -> None:
        """Before a physics step: parked objects back at their park pose, locked joints at their value, all still."""
        for name in state.parked:
            event = self._by_name[name]
            data.qpos[list(event.qpos)] = [*self.park[name], 1.0, 0.0, 0.0, 0.0]
            data.qvel[list(event.dof)] = 0.0
        self.hold_locked(state, data)

    def hold_locked(self, state: EventState, data: mujoco.MjData) -> None:
        """Locked joints back at their value and still (the CPU backend also calls this after every physics step
        while a joint is locked)."""
        for name, value in state.locked.items():
            event = self._by_name[name]
            data.qpos[event.qpos[0]] = value
            data.qvel[event.dof[0]] = 0.0

    def fire(self, state: EventState, data: mujoco.MjData, step: int, triggers: np.ndarray) -> bool:
        """After a step's predicates: run every event whose trigger holds for the first time. Returns whether the
        state changed (the caller then recomputes the derived quantities with `mj_forward`)."""
        changed = False
        for k, event in enumerate(self.events):
            if k in state.fired:
                continue
            due = bool(triggers[event.trigger]) if event.trigger >= 0 else step >= event.at_step
            if due:
                state.fired.add(k)
                self._apply(event, state, data)
                changed = True
        if changed:
            self.hold(state, data)
        return changed

    def _apply(self, event: Event, state: EventState, data: mujoco.MjData) -> None:
        qpos, name = list(event.qpos), event.name
        if event.action in ("hide", "remove"):
            state.parked.setdefault(name, data.qpos[qpos].copy())
        elif event.action in ("show", "spawn") and name in state.parked:
            data.qpos[qpos] = state.parked.pop(name)
            data.qvel[list(event.dof)] = 0.0
        elif event.action == "cover":
            state.parked.pop(name, None)
            target = self.model.body(self._target_body(event.target)).id
            pose = self.init_qpos[qpos].copy()
            pose[:2] = data.xpos[target][:2]
            data.qpos[qpos] = pose
            data.qvel[list(event.dof)] = 0.0
        elif event.action == "lock":
            state.locked[name] = float(data.qpos[qpos[0]])
        elif event.action == "unlock":
            state.locked.pop(name, None)

    def _target_body(self, target: str | None) -> str:
        return self.plan.objects[str(target).split("/", 1)[0]]["body"]


def compile_events(plan: Any, model: mujoco.MjModel) -> WorldEvents | None:
    """The plan's events resolved against its model (None when the task has none). Raises EventError."""
    specs = plan.program.get("events", [])
    if not specs:
        return None
    events, trigger = [], 0
    for i, spec in enumerate(specs):
        action = next(a for a in ACTIONS if a in spec)
        if "when" in spec:
            index, at_step = trigger, -1
            trigger += 1
        else:
            index, at_step = -1, int(spec["at_step"])
        value = spec[action]
        name, target = (value[0], value[1]) if action == "cover" else (value, None)
        path = ("events", i, action)
        if action in JOINT_ACTIONS:
            jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
            if "/" not in name or jid < 0:
                obj = name.split("/", 1)[0]
                known = plan.objects.get(obj, {}).get("joints", [])
                raise EventError(f"{action}: no joint {name!r} (joints of {obj!r}: {', '.join(known) or 'none'})",
                                 path)
            qpos, dof = (int(model.jnt_qposadr[jid]),), (int(model.jnt_dofadr[jid]),)
        else:
            free = plan.objects.get(name, {}).get("free_joint")
            if not free:
                raise EventError(f"{action}: {name!r} is not a movable object of the scene (events move objects "
                                 "with a free joint, not fixtures)", path)
            joint = model.joint(free)
            qpos = tuple(range(int(joint.qposadr[0]), int(joint.qposadr[0]) + 7))
            dof = tuple(range(int(joint.dofadr[0]), int(joint.dofadr[0]) + 6))
            if target is not None and target.split("/", 1)[0] not in plan.objects:
                raise EventError(f"cover: {target!r} is not an object of the scene", path)
        events.append(Event(action, index, at_step, name, qpos, dof, target))
    return WorldEvents(plan, model, events)
