"""The `conveyor` actor: a belt that carries objects across the table, one after another.

Spec (task schema `$defs/conveyor`, choices drawn per episode by `dojo.compiler.actor_draws`): `belt` (a region:
where the belt runs), `direction` ([dx, dy], along the belt), `speed` (m/s), `items` (the objects it carries, in
order; a number in the list is a pause of that many control steps), `spacing` (control steps between two items), `start_step` and `at_end` (`remove`: the item leaves the
scene, `stop`: it stays at the end, `loop`: it starts over). Items are absent until their turn; then each appears
at the belt's upstream end, where its start pose puts it (height and attitude), and moves with the belt.

The belt moves what lies on it kinematically: before every physics step an item that still rests on the belt and
that the robot does not touch is advanced by speed x control period and held still (a belt drives what sits on it,
it does not throw it). An item the robot touches is left to the physics, so a gripper closing on it stops it, and
one lifted off the belt is no longer carried.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

PARKED = np.array([-2.0, -3.1, 0.3])
"""Where items wait for their turn and go when removed (behind the robot, out of view); the k-th is 0.4 m along x."""
ON_BELT = 0.015
"""An item rests on the belt while its height is within this of its height on the belt (m)."""
WAITING, CARRIED, LEFT, DONE = "waiting", "carried", "left", "done"


@dataclass
class _Item:
    name: str
    qpos: list[int]
    dof: list[int]
    geoms: np.ndarray
    start: np.ndarray
    """qpos of the item where it enters the belt."""
    reach: float
    """How far it reaches along the belt from its centre: it leaves the belt when its front passes the end."""


@dataclass
class ConveyorState:
    status: dict[str, str] = field(default_factory=dict)


class Conveyor:
    """One compiled conveyor of a plan (see the module docstring)."""

    def __init__(self, plan: Any, model: mujoco.MjModel, spec: dict[str, Any]) -> None:
        self.model = model
        self.speed = float(spec["speed"])
        self.spacing = int(spec.get("spacing", 50))
        self.start_step = int(spec.get("start_step", 0))
        self.at_end = spec.get("at_end", "remove")
        region = plan.regions[spec["belt"]]
        d = np.asarray(spec.get("direction", [1.0, 0.0]), dtype=float)
        self.direction = d / np.linalg.norm(d)
        self.center = np.asarray(region["center"], dtype=float)
        size = np.asarray(region["size"], dtype=float)
        self.half_length = float(np.abs(self.direction) @ size) / 2.0
        self.dt = float(plan.n_substeps * model.opt.timestep)
        bases = [model.body(f"{side}_base").id for side in ("left", "right")]
        self._is_robot = np.isin(model.body_rootid[model.geom_bodyid], bases)
        """Per geom, whether it is the robot's: `_touched` runs before every physics step, and looking contacts up
        here instead of `np.isin` on each (three calls an item) was 22 of the 154 s that 300 episodes of conveyor
        and event tasks took on the CPU backend in the protocol's run on a GPU machine (2026-12-03, cProfile)."""
        init = np.asarray(plan.init_qpos, dtype=float)
        self.items, self.enters = [], []
        step = self.start_step
        for name in spec["items"]:
            if not isinstance(name, str):
                step += int(name)
                continue
            self.enters.append(step)
            step += self.spacing
            joint = model.joint(plan.objects[name]["free_joint"])
            qpos = list(range(int(joint.qposadr[0]), int(joint.qposadr[0]) + 7))
            start = init[qpos].copy()
            reach = self._along_half(model, plan.objects[name]["geoms"])
            start[:2] = self.center - self.direction * (self.half_length - reach)
            self.items.append(_Item(name, qpos, list(range(int(joint.dofadr[0]), int(joint.dofadr[0]) + 6)),
                                    np.asarray([model.geom(g).id for g in plan.objects[name]["geoms"]]), start, reach))

    def _along_half(self, model: mujoco.MjModel, geoms: list[str]) -> float:
        """How far the item reaches along the belt from its centre (its bounding radius in the plane)."""
        return max(float(np.linalg.norm(model.geom(g).pos[:2])) + float(model.geom_rbound[model.geom(g).id])
                   for g in geoms)

    def start(self, data: mujoco.MjData) -> ConveyorState:
        state = ConveyorState({item.name: WAITING for item in self.items})
        self.hold(state, data, 0)
        return state

    def hold(self, state: ConveyorState, data: mujoco.MjData, step: int) -> None:
        """Before the physics step after control step `step`: bring items on in turn, move those on the belt."""
        touched = self._touched(data)
        for k, item in enumerate(self.items):
            status = state.status[item.name]
            if status == WAITING and step >= self.enters[k]:
                data.qpos[item.qpos] = item.start
                status = CARRIED
            if status == CARRIED and (item.name in touched or abs(data.qpos[item.qpos[2]] - item.start[2]) > ON_BELT):
                status = LEFT  # in the robot's hands or off the belt: the physics has it from now on
            if status == CARRIED:
                along = float((data.qpos[item.qpos[:2]] - self.center) @ self.direction)
                if along + self.speed * self.dt > self.half_length - item.reach:
                    status = {"remove": DONE, "loop": CARRIED, "stop": LEFT}[self.at_end]
                    if self.at_end == "loop":
                        data.qpos[item.qpos] = item.start
                else:
                    data.qpos[item.qpos[:2]] += self.direction * self.speed * self.dt
                data.qvel[item.dof] = 0.0
            if status in (WAITING, DONE):
                data.qpos[item.qpos] = [*(PARKED + [0.4 * k, 0.0, 0.0]), 1.0, 0.0, 0.0, 0.0]
                data.qvel[item.dof] = 0.0
            state.status[item.name] = status

    def _touched(self, data: mujoco.MjData) -> set[str]:
        """The items a robot geom touches now."""
        n = data.ncon
        if n == 0:
            return set()
        g1, g2 = data.contact.geom1[:n], data.contact.geom2[:n]
        held = np.zeros(self._is_robot.size, bool)  # geoms in contact with a robot geom
        held[g2[self._is_robot[g1]]] = True
        held[g1[self._is_robot[g2]]] = True
        return {item.name for item in self.items if held[item.geoms].any()}
