"""The `demonstrator` actor: another agent across the table puts its objects into a container, one at a time, in an
order drawn per episode, for the robot to watch (and, in imitate_sorting_sequence, to repeat with its own).

Spec (task schema `$defs/demonstrator`): `objects` (its objects; a list inside the list comes in an order drawn from
the episode's seed, `dojo.compiler.actor_draws`), `into` (a placement annotation, `container/inside`), `start_step`,
`move_steps` (control steps a move takes) and `pause` (control steps between moves). It is an unseen hand: each
object rises from where it lies, travels on an arc and is lowered into the container, to its own spot there (the
container's placement box is divided into one spot per object, in the order they come), held on its path; at the
end of its move it is let go and settles under the physics.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

ARC = 0.18
"""How high above the higher of its two ends an object passes, half way (m)."""
RELEASE = 0.01
"""Height above its spot's floor at which an object is let go (m)."""


@dataclass
class DemonstratorState:
    start: dict[str, np.ndarray]
    """Where each object lay when its move began (filled as moves begin)."""


class Demonstrator:
    """One compiled demonstrator of a plan (see the module docstring)."""

    def __init__(self, plan: Any, model: mujoco.MjModel, spec: dict[str, Any]) -> None:
        self.order = [n for n in spec["objects"] if isinstance(n, str)]
        self.start_step = int(spec.get("start_step", 0))
        self.move_steps = int(spec.get("move_steps", 50))
        self.pause = int(spec.get("pause", 15))
        data = plan.initial_data(model)
        owner, annotation = spec["into"].split("/", 1)
        site = model.site(plan.objects[owner]["sites"][annotation]).id
        centre, rot, half = data.site_xpos[site], data.site_xmat[site].reshape(3, 3), model.site_size[site]
        n = len(self.order)
        cols = int(np.ceil(np.sqrt(n * half[0] / max(half[1], 1e-6))))
        rows = int(np.ceil(n / cols))
        spots = [(((c + 0.5) / cols - 0.5) * 2 * half[0], ((r + 0.5) / rows - 0.5) * 2 * half[1])
                 for r in range(rows) for c in range(cols)][:n]
        self.joint = {name: model.joint(plan.objects[name]["free_joint"]) for name in self.order}
        init = np.asarray(plan.init_qpos, dtype=float)
        self.goal = {}
        for name, (u, v) in zip(self.order, spots):
            goal = init[self._qpos(name)].copy()  # its frame is the bottom of its footprint: on the floor, let go
            goal[:3] = centre + rot @ np.array([u, v, -half[2]]) + [0.0, 0.0, RELEASE]
            self.goal[name] = goal

    def _qpos(self, name: str) -> list[int]:
        adr = int(self.joint[name].qposadr[0])
        return list(range(adr, adr + 7))

    def start(self, data: mujoco.MjData) -> DemonstratorState:
        return DemonstratorState({})

    def hold(self, state: DemonstratorState, data: mujoco.MjData, step: int) -> None:
        """Before the physics step after control step `step`: the object in its move (if any) at its point of the arc."""
        t = step - self.start_step
        period = self.move_steps + self.pause
        if t < 0 or t >= period * len(self.order):
            return
        k, phase = divmod(t, period)
        if phase >= self.move_steps:
            return
        name = self.order[k]
        qpos = self._qpos(name)
        if name not in state.start:
            state.start[name] = data.qpos[qpos].copy()
        a, b = state.start[name], self.goal[name]
        s = (phase + 1) / self.move_steps
        smooth = s * s * (3.0 - 2.0 * s)
        pose = a + (b - a) * smooth
        pose[2] += 4.0 * (max(a[2], b[2]) + ARC - (a[2] + b[2]) / 2.0) * s * (1.0 - s)
        pose[3:] = a[3:]
        data.qpos[qpos] = pose
        adr = int(self.joint[name].dofadr[0])
        data.qvel[adr:adr + 6] = 0.0
