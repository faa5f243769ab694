"""The `demonstrator` actor: another agent across the table puts its objects into a container, one at a time, in an
order drawn per episode, for the robot to watch (and, in imitate_sorting_sequence, to repeat with its own).

Spec (task schema `$defs/demonstrator`): `objects` (its objects; a list inside the list comes in an order drawn from
the episode's seed, `dojo.compiler.actor_draws`), `into` (a placement annotation, `container/inside`), `start_step`,
`move_steps` (control steps a move takes), `pause` (control steps between moves) and `arm`. Each object rises from
where it lies, travels on an arc and is lowered into the container, to its own spot there (the container's
placement box is divided into one spot per object, in the order they come), held on its path; at the end of its
move it is let go and settles under the physics.

With `arm: {upper, forearm, hand}` (three scene entries whose assets are `base: kinematic`, placed opposite the
robot) the moves are made by a visible arm: its hand reaches the object during the pause before each move, holds
it by its `grip` frame on the way, and retracts to rest after the last. The upper link turns about its origin (the
shoulder, where its entry is placed) and reaches to its `tip` frame, the elbow; the forearm from there to the wrist,
the hand's origin. Both links bend in the vertical plane through shoulder and wrist, elbow up (two-link inverse
kinematics, link lengths read off their `tip` frames). The arm is kinematic and visual only: it moves nothing, the
objects are moved as without it. Without `arm` it is an unseen hand.
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


GRIP_DEPTH = 0.015
"""How far below an object's top the hand's `grip` frame holds it (m)."""
REST = np.array([0.25, 0.0])
"""The arm's rest: its wrist this far from the shoulder towards the container (horizontally) and up (m)."""


@dataclass
class DemonstratorState:
    start: dict[str, np.ndarray]
    """Where each object lay when its move began (filled as moves begin)."""
    wrist: np.ndarray | None = None
    """Where the arm's wrist was at the end of the last move or approach (the start of the next approach)."""


class Arm:
    """The demonstrator's visible arm: three kinematic bodies posed from a wrist position (module docstring)."""

    def __init__(self, plan: Any, model: mujoco.MjModel, data: mujoco.MjData, spec: dict[str, str],
                 towards: np.ndarray) -> None:
        self.mocap = {}
        for part in ("upper", "forearm", "hand"):
            body = model.body(plan.objects[spec[part]]["body"])
            if body.mocapid[0] < 0:
                raise ValueError(f"demonstrator arm {part} '{spec[part]}' must be an asset with base: kinematic")
            self.mocap[part] = int(body.mocapid[0])
        self.shoulder = data.xpos[model.body(plan.objects[spec["upper"]]["body"]).id].copy()

        def local(name: str, annotation: str) -> np.ndarray:
            obj = plan.objects[name]
            return model.site(obj["sites"][annotation]).pos.copy()

        self.upper = float(local(spec["upper"], "tip")[0])
        self.forearm = float(local(spec["forearm"], "tip")[0])
        self.grip = local(spec["hand"], "grip")
        out = towards[:2] - self.shoulder[:2]
        out = out / max(float(np.linalg.norm(out)), 1e-9)
        self.rest = self.shoulder + [REST[0] * out[0], REST[0] * out[1], REST[1]]

    def holding(self, point: np.ndarray) -> np.ndarray:
        """The wrist position whose hand holds an object at `point` (its grip frame there; the hand hangs down)."""
        return point - self.grip

    def pose(self, data: mujoco.MjData, wrist: np.ndarray) -> None:
        """Write the three bodies' poses for the wrist at `wrist` (out of reach: the arm stretched towards it)."""
        s = self.shoulder
        d = wrist - s
        dist = float(np.linalg.norm(d))
        u = d / max(dist, 1e-9)
        dist = float(np.clip(dist, abs(self.upper - self.forearm) + 1e-6, self.upper + self.forearm - 1e-6))
        up = np.array([0.0, 0.0, 1.0]) - u[2] * u  # in the vertical plane through s and the wrist, elbow up
        up = up / np.linalg.norm(up) if np.linalg.norm(up) > 1e-6 else np.array([1.0, 0.0, 0.0])
        cos_a = (self.upper ** 2 + dist ** 2 - self.forearm ** 2) / (2.0 * self.upper * dist)
        a = float(np.arccos(np.clip(cos_a, -1.0, 1.0)))
        elbow = s + self.upper * (np.cos(a) * u + np.sin(a) * up)
        reach = s + dist * u
        for part, start, end in (("upper", s, elbow), ("forearm", elbow, reach)):
            data.mocap_pos[self.mocap[part]] = start
            data.mocap_quat[self.mocap[part]] = _pointing(end - start)
        data.mocap_pos[self.mocap["hand"]] = reach
        data.mocap_quat[self.mocap["hand"]] = _pointing(np.array([*(reach - s)[:2], 0.0]))


def _pointing(direction: np.ndarray) -> np.ndarray:
    """The quaternion turning +x onto `direction` with +y kept horizontal (a link's or the hand's attitude)."""
    x = direction / max(float(np.linalg.norm(direction)), 1e-9)
    y = np.cross([0.0, 0.0, 1.0], x)
    y = y / np.linalg.norm(y) if np.linalg.norm(y) > 1e-9 else np.array([0.0, 1.0, 0.0])
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.column_stack([x, y, np.cross(x, y)]).ravel())
    return quat


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
        self.height = {name: 2.0 * float(plan.objects[name]["half_extents"][2]) for name in self.order}
        self.arm = Arm(plan, model, data, spec["arm"], centre) if "arm" in spec else None

    def _qpos(self, name: str) -> list[int]:
        adr = int(self.joint[name].qposadr[0])
        return list(range(adr, adr + 7))

    def start(self, data: mujoco.MjData) -> DemonstratorState:
        state = DemonstratorState({})
        if self.arm is not None:
            state.wrist = self.arm.rest.copy()
            self.arm.pose(data, state.wrist)
        return state

    def hold(self, state: DemonstratorState, data: mujoco.MjData, step: int) -> None:
        """Before the physics step after control step `step`: the object in its move (if any) at its point of the
        arc, and the arm (if any) where it holds it or on its way to the next object or to rest."""
        t = step - self.start_step
        period = self.move_steps + self.pause
        k, phase = divmod(t, period)
        if 0 <= t < period * len(self.order) and phase < self.move_steps:
            self._move(state, data, self.order[k], phase)
        elif self.arm is not None:
            self._reach(state, data, t, period)

    def _reach(self, state: DemonstratorState, data: mujoco.MjData, t: int, period: int) -> None:
        """The arm between moves: during the `pause` before a move its hand goes to the object's grip point (the
        first approach may start before `start_step`); after the last move it goes back to rest."""
        arm = self.arm
        k = (t + self.pause) // period  # the move this pause leads to (0: the first, before start_step)
        into = (t + self.pause) - k * period  # control steps into the approach
        if 0 <= k < len(self.order) and into < self.pause:
            name = self.order[k]
            qpos = data.qpos[self._qpos(name)]
            goal = arm.holding(qpos[:3] + [0.0, 0.0, self.height[name] - GRIP_DEPTH])
        else:
            into = t - period * len(self.order) + self.pause if k >= len(self.order) else self.pause
            goal = arm.rest
        s = min(1.0, (into + 1) / max(self.pause, 1))
        wrist = state.wrist + (goal - state.wrist) * (s * s * (3.0 - 2.0 * s))
        arm.pose(data, wrist)
        if s >= 1.0:
            state.wrist = goal.copy()

    def _move(self, state: DemonstratorState, data: mujoco.MjData, name: str, phase: int) -> None:
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
        if self.arm is not None:
            state.wrist = self.arm.holding(pose[:3] + [0.0, 0.0, self.height[name] - GRIP_DEPTH])
            self.arm.pose(data, state.wrist)
