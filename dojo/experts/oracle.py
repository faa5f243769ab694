"""The `oracle` policy: PRIVILEGED. It runs each task's scripted expert from the simulator state.

It is a reference, not a contestant: it reads the full simulator state (`obs["privileged"]`: qpos, qvel, the
plan's hash and file) that no real robot and no submitted policy gets, and its metadata says so
(`extra: {"privileged": true}`), so every result row it produces carries the mark. It exists for tests (every
built-in task must be solvable: DESIGN section 7), demonstrations and data collection.

Served like any policy: `dojo run policy=oracle`, or `dojo policy serve policy=dojo.experts.oracle:OraclePolicy`
on the machine that holds the plan files (it reads the plan file the observation names). It acts in the joint
mode: per environment it keeps one scripted expert (a state machine over the task's `expert:` skills, see
`dojo.experts.skills`) and its own MjData of the plan's model, set to the observed qpos before each decision.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Hashable, Sequence
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from xpolicylab.model import Model, Observation, PolicyMetadata

from dojo.experts.skills import SkillContext, program

PRIVILEGED = "privileged"


class ScriptedExpert:
    """One episode of a task's scripted expert: pulls skill segments as the rows run out."""

    def __init__(self, plan: Any, steps: list[dict[str, Any]], shifts: dict[str, np.ndarray] | None = None) -> None:
        self.plan = plan
        self.shifts = shifts
        """Annotations the expert believes elsewhere (`Scene.shifts`): none for the oracle itself."""
        self.model = plan.model()
        self.data = mujoco.MjData(self.model)
        self.ctx: SkillContext | None = None
        self.steps = steps
        self.rows: deque[np.ndarray] = deque()
        self.program = None

    def observe(self, qpos: np.ndarray, qvel: np.ndarray) -> None:
        self.data.qpos[:] = qpos
        self.data.qvel[:] = qvel
        mujoco.mj_forward(self.model, self.data)
        if self.ctx is None:
            self.ctx = SkillContext(self.plan, self.model, self.data, self.shifts)
            self.program = program(self.ctx, self.steps)

    def act(self, k: int) -> np.ndarray:
        """The next k action rows (joint mode); holds the last command once the program is done."""
        assert self.ctx is not None, "observe() first"
        while len(self.rows) < k and self.program is not None:
            try:
                self.rows.extend(next(self.program))
            except StopIteration:
                self.program = None
        if len(self.rows) < k:
            last = self.ctx.rows([self.ctx.q.copy()])[0]
            self.rows.extend([last] * (k - len(self.rows)))
        return np.stack([self.rows.popleft() for _ in range(k)])


class OraclePolicy(Model):
    """PRIVILEGED scripted-expert policy (reads the simulator state; never a leaderboard entry).

    Config: `chunk_size` (rows per call, default 4), `packs` (extra task-pack folders whose tasks' experts it
    should know), `embodiment`.
    """

    def __init__(self, config: dict[str, Any] | None = None) -> None:
        super().__init__(config)
        self.chunk_size = int(self.config.get("chunk_size", 4))
        self.embodiment = str(self.config.get("embodiment", "arx_x5_bimanual"))
        self.packs = [Path(p) for p in self.config.get("packs", []) or []]
        self._plans: dict[str, Any] = {}
        self._experts: dict[Hashable, ScriptedExpert] = {}
        self._obs: dict[Hashable, Observation] = {}
        self._library = None

    @property
    def metadata(self) -> PolicyMetadata:
        return PolicyMetadata(name="oracle", action_mode="joint", chunk_size=self.chunk_size, action_dim=14,
                              embodiment=self.embodiment, cameras=(), image_width=None, image_height=None,
                              batch=True, extra={PRIVILEGED: True, "reads": "simulator state (qpos, plan)"})

    # ---- plans and experts ----

    def _plan(self, privileged: dict[str, Any]) -> Any:
        digest = str(privileged["plan_hash"])
        if digest not in self._plans:
            from dojo.compiler.plan import Plan

            path = privileged.get("plan_path")
            if not path:
                raise ValueError("the oracle needs obs['privileged']['plan_path'] (a backend built with "
                                 "privileged=True and the plan files)")
            self._plans[digest] = Plan.load(Path(str(path)))
        return self._plans[digest]

    def expert_steps(self, task: str) -> list[dict[str, Any]]:
        """The task's `expert:` list, from the built-in specs (and `packs`). A pack with a broken file still has
        experts for its other tasks (`dojo validate --strict` runs them beside the one it reports)."""
        if self._library is None:
            from dojo.compiler.spec_library import SpecLibrary

            self._library = SpecLibrary.load(self.packs, strict=False)
        return list(self._library.get("task", task).data.get("expert", []))

    def new_expert(self, plan: Any) -> ScriptedExpert:
        """The scripted expert of one episode (the memoryless variant overrides what it knows)."""
        return ScriptedExpert(plan, self.expert_steps(plan.task))

    def _expert(self, env_id: Hashable, obs: Observation) -> ScriptedExpert:
        privileged = obs.get(PRIVILEGED)
        if privileged is None:
            raise ValueError("the oracle is a privileged policy: run it on a backend with privileged=True "
                             "(dojo run does so when the policy's metadata says extra.privileged)")
        expert = self._experts.get(env_id)
        if expert is None or expert.plan.hash != privileged["plan_hash"]:
            plan = self._plan(privileged)
            expert = self._experts[env_id] = self.new_expert(plan)
        expert.observe(np.asarray(privileged["qpos"], np.float64), np.asarray(privileged["qvel"], np.float64))
        return expert

    # ---- Model ----

    def reset(self) -> None:
        self._experts.clear()
        self._obs.clear()

    def reset_batch(self, env_ids: Sequence[Hashable]) -> None:
        for env_id in env_ids:
            self._experts.pop(env_id, None)
            self._obs.pop(env_id, None)

    def update_obs(self, obs: Observation) -> None:
        self._obs[None] = obs

    def get_action(self) -> np.ndarray:
        return self.get_action_batch([None])[0]

    def update_obs_batch(self, obs_list: Sequence[Observation], env_ids: Sequence[Hashable]) -> None:
        self._obs.update(zip(env_ids, obs_list, strict=True))

    def get_action_batch(self, env_ids: Sequence[Hashable]) -> np.ndarray:
        chunks = [self._expert(e, self._obs[e]).act(self.chunk_size) for e in env_ids]
        return np.stack(chunks).astype(np.float32)
