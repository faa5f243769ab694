"""The `opponent` actor: a second player of a board game that takes its turn after the robot's.

Spec (task schema `$defs/opponent`): `board` (a fixture), `cells` (its placement annotations that are the places),
`pieces` (the group of the opponent's pieces, played in name order), `after` (the group of the robot's
pieces), `rule` and `delay`. The opponent moves once more of the robot's pieces lie settled on the board than of
its own, `delay` control steps after that became so: it puts its next piece flat on a free cell (its start
attitude, resting on the board), chosen by its rule (`dojo.backends.opponent_rules`):
- `random`: uniformly at random among the free cells. The choice is made at compile time as a preference order
  over all cells drawn from the episode's seed (`dojo.compiler.actor_draws`), of which it takes the first free
  cell: a fixed strategy per episode, in the plan, so a replay is exact.
- `win_then_block`: completes one of its own `lines` if it can, else blocks one of the robot's, else takes the
  first free cell of `prefer` (default: `cells` as listed), e.g. centre, corners, edges.
A piece lies on a cell when its origin (the centre of its footprint) is within the cell's box in the plane and at
the board's height, it is still, and no robot geom touches it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from dojo.backends.opponent_rules import RULES

SETTLED = 0.03
"""A piece moving slower than this (m/s) has been let go."""
HEIGHT = 0.005
"""A piece whose origin is within this of the board's surface lies on the board (m)."""
MARGIN = 0.01
"""A piece's origin may be this far outside a cell's box in the plane and still count as on it (m)."""


@dataclass
class OpponentState:
    played: int = 0
    waiting_since: int | None = None
    placed: dict[str, int] = field(default_factory=dict)
    """Opponent piece -> index of the cell it was put on."""


class Opponent:
    """One compiled opponent of a plan (see the module docstring)."""

    def __init__(self, plan: Any, model: mujoco.MjModel, spec: dict[str, Any]) -> None:
        self.delay = int(spec.get("delay", 20))
        data = plan.initial_data(model)
        sites = plan.objects[spec["board"]]["sites"]
        cells = list(spec["cells"])
        self.cells = np.array([data.site_xpos[model.site(sites[c]).id] for c in cells])
        self.half = np.array([model.site_size[model.site(sites[c]).id][:2] for c in cells])
        self.order = [cells.index(c) for c in spec["order"]]
        self.lines = [[cells.index(c) for c in line] for line in spec.get("lines", [])]
        self.rule = RULES[spec.get("rule", "random")]
        self.surface = float(np.mean(self.cells[:, 2]))
        members = lambda group: sorted(n for n, o in plan.objects.items() if o.get("group") == group)  # noqa: E731
        self.mine, self.theirs = members(spec["pieces"]), members(spec["after"])
        self.joint = {n: model.joint(plan.objects[n]["free_joint"]) for n in self.mine + self.theirs}
        self.geoms = {n: np.asarray([model.geom(g).id for g in plan.objects[n]["geoms"]]) for n in self.theirs}
        bases = [model.body(f"{side}_base").id for side in ("left", "right")]
        self.robot_geoms = np.flatnonzero(np.isin(model.body_rootid[model.geom_bodyid], bases))
        self.start_pose = {n: np.asarray(plan.init_qpos, dtype=float)[self._qpos(n)] for n in self.mine}

    def _qpos(self, name: str) -> list[int]:
        adr = int(self.joint[name].qposadr[0])
        return list(range(adr, adr + 7))

    def _cell_of(self, data: mujoco.MjData, name: str) -> int | None:
        """The cell the piece lies on, if any."""
        pos = data.qpos[self._qpos(name)[:3]]
        if abs(pos[2] - self.surface) > HEIGHT:
            return None
        inside = np.all(np.abs(self.cells[:, :2] - pos[:2]) <= self.half + MARGIN, axis=1)
        return int(np.argmax(inside)) if inside.any() else None

    def _settled(self, data: mujoco.MjData, name: str) -> bool:
        adr = int(self.joint[name].dofadr[0])
        if np.linalg.norm(data.qvel[adr:adr + 3]) > SETTLED:
            return False
        n = data.ncon
        g1, g2 = data.contact.geom1[:n], data.contact.geom2[:n]
        mine = np.isin(g1, self.geoms[name]) | np.isin(g2, self.geoms[name])
        robot = np.isin(g1, self.robot_geoms) | np.isin(g2, self.robot_geoms)
        return not np.any(mine & robot)

    def start(self, data: mujoco.MjData) -> OpponentState:
        return OpponentState()

    def hold(self, state: OpponentState, data: mujoco.MjData, step: int) -> None:
        """Before a physics step: the opponent's move, once the robot has made one more than it and `delay` passed."""
        if state.played >= len(self.mine):
            return
        robot_cells = {c for n in self.theirs if (c := self._cell_of(data, n)) is not None and self._settled(data, n)}
        if len(robot_cells) <= state.played:
            state.waiting_since = None
            return
        if state.waiting_since is None:
            state.waiting_since = step
        if step - state.waiting_since < self.delay:
            return
        own = {c for n in self.mine if (c := self._cell_of(data, n)) is not None}
        robot = {c for n in self.theirs if (c := self._cell_of(data, n)) is not None}
        cell = self.rule(self.order, self.lines, own, robot)
        if cell is None:
            return
        name = self.mine[state.played]
        pose = self.start_pose[name].copy()
        pose[:2] = self.cells[cell, :2]
        pose[2] = self.surface + 0.001
        data.qpos[self._qpos(name)] = pose
        adr = int(self.joint[name].dofadr[0])
        data.qvel[adr:adr + 6] = 0.0
        state.placed[name] = cell
        state.played += 1
        state.waiting_since = None
