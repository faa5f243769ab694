"""The CPU reference backend: plain MuJoCo, one MjData per environment slot, stepped across a thread pool.

`mujoco.mj_step` releases the GIL, so the slots of one control step run on all cores (one `mj_step(nstep=
n_substeps)` call per slot per control step; the calling thread takes one share of the slots, helper threads
the others). Action conversion and predicate evaluation are batched NumPy in
the calling thread: actions with `dojo.backends.actions`, predicates with `dojo.backends.predicate_program`
(grouped by program layout, so slots of one task are evaluated in one call). IK for the ee modes runs in the
workers, one scratch MjData per slot.

Models are compiled once per plan hash and kept: `reset` of a slot only rewrites its MjData (no model
rebuild), and refilling a slot with another plan of an already seen hash costs no compilation either.
All slots must share one embodiment, since an action batch has one layout.
"""

from __future__ import annotations

import os
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from dojo.backends import actions as A
from dojo.backends.base import (
    END_NONFINITE,
    END_UNSTABLE,
    Backend,
    Observation,
    StepResult,
    checked_actions,
    end_after_step,
    envelope,
    refuse_ended,
    resolve_ids,
)
from dojo.backends.predicate_program import CompiledProgram, ProgramLayout, compile_program, init_memory, program_step
from dojo.backends.predicate_state import mujoco_state
from dojo.backends.world_actors import Actor, compile_actors
from dojo.backends.world_events import EventState, WorldEvents, compile_events
from dojo.backends.mujoco.kinematics import ArmKinematics, RobotIndex

DIVERGED = (mujoco.mjtWarning.mjWARN_BADQPOS, mujoco.mjtWarning.mjWARN_BADQVEL, mujoco.mjtWarning.mjWARN_BADQACC)
"""MuJoCo's warnings for a diverged simulation; it resets the state when it raises them."""
CACHED_PLANS = 64
"""Compiled plans kept beyond those in the slots (refilling a slot with one of them costs no compilation)."""


@dataclass
class _Compiled:
    """What is built once per plan hash: the model, its predicate program and its robot index."""

    model: mujoco.MjModel
    program: CompiledProgram
    robot: RobotIndex
    params: dict[str, np.ndarray]
    """The program's params with a leading axis of 1, ready to concatenate over slots."""
    events: WorldEvents | None = None
    """The task's events (`dojo.backends.world_events`), run in `step`; None when it has none."""
    actors: list[Actor] = field(default_factory=list)
    """The task's actors (`dojo.backends.world_actors`), run before every physics step."""


@dataclass
class _Slot:
    plan: Any
    compiled: _Compiled
    data: mujoco.MjData
    kinematics: ArmKinematics | None = None
    memory: dict[str, np.ndarray] = field(default_factory=dict)
    step: int = 0
    done: bool = False
    end_reason: str | None = None
    success: bool = False
    score: float = 0.0
    stage_step: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    terms: dict[str, bool] = field(default_factory=dict)
    clipped_total: int = 0
    events: EventState | None = None
    actors: list[Any] = field(default_factory=list)
    """Each actor's state for this episode."""


class MujocoBackend(Backend):
    """CPU reference backend. `cameras` (subset of the robot's) are rendered into observations when given."""

    name = "mujoco"

    def __init__(self, num_threads: int | None = None, cameras: Sequence[str] = (), width: int = 640,
                 height: int = 480, depth: bool = False, privileged: bool = False,
                 plan_paths: Mapping[str, str] | None = None) -> None:
        """`privileged`: observations also carry `privileged: {qpos, qvel, plan_hash, plan_path}`, the full
        simulator state, for privileged reference policies only (the `oracle`); `plan_paths` maps plan hashes
        to plan files for its `plan_path` (None when unknown)."""
        self.privileged, self.plan_paths = privileged, dict(plan_paths or {})
        self.num_threads = num_threads or os.cpu_count() or 1
        self.cameras, self.width, self.height, self.depth = tuple(cameras), width, height, depth
        self._renderers: Any = None  # a RendererCache, made on the first rendered observation
        # The calling thread steps one share of the slots itself: a pool of num_threads - 1 helpers, and no
        # thread hand-off at all for one thread or one slot (hand-offs cost milliseconds on a busy machine).
        self._pool = ThreadPoolExecutor(max(1, self.num_threads - 1), thread_name_prefix="dojo-mujoco")
        self._compiled: OrderedDict[str, _Compiled] = OrderedDict()
        self._prefetcher = ThreadPoolExecutor(1, thread_name_prefix="dojo-mujoco-prefetch")
        self._pending: dict[str, Future[_Compiled]] = {}
        self._layouts: dict[ProgramLayout, ProgramLayout] = {}
        self._slots: list[_Slot] = []

    # ---- plans and slots ----

    @property
    def num_envs(self) -> int:
        return len(self._slots)

    def prefetch(self, plans: Sequence[Any]) -> None:
        """Compile these plans' models in a background thread, so that a later refill with them costs a reset
        (well under a millisecond) instead of a model compilation (tens of milliseconds)."""
        for plan in plans:
            if plan.hash not in self._compiled and plan.hash not in self._pending:
                self._pending[plan.hash] = self._prefetcher.submit(_build, plan)

    def _compile(self, plan: Any) -> _Compiled:
        """The compiled entry of a plan's hash, built on first use (or taken from `prefetch`); the least
        recently used entries beyond CACHED_PLANS that no slot holds are dropped, so a long suite does not keep
        every model alive."""
        if plan.hash not in self._compiled:
            pending = self._pending.pop(plan.hash, None)
            compiled = pending.result() if pending is not None else _build(plan)
            layout = compiled.program.layout
            compiled.program.layout = self._layouts.setdefault(layout, layout)
            self._compiled[plan.hash] = compiled
            in_use = {s.plan.hash for s in self._slots} | {plan.hash}
            for old in [h for h in self._compiled if h not in in_use][:max(0, len(self._compiled) - CACHED_PLANS)]:
                del self._compiled[old]
        self._compiled.move_to_end(plan.hash)
        return self._compiled[plan.hash]

    @staticmethod
    def _check_embodiment(plans: Sequence[Any]) -> None:
        known = {p.embodiment for p in plans}
        if len(known) > 1:
            raise ValueError(f"one backend runs one embodiment (action layout); got {sorted(known)}")

    def load(self, plans: Sequence[Any]) -> None:
        self._slots = []
        self._check_embodiment(plans)
        for plan in plans:
            compiled = self._compile(plan)
            slot = _Slot(plan, compiled, mujoco.MjData(compiled.model))
            self._restart(slot)
            self._slots.append(slot)

    def _restart(self, slot: _Slot) -> None:
        """Put a slot at its plan's initial state with fresh episode bookkeeping (model and MjData reused)."""
        model, data, plan = slot.compiled.model, slot.data, slot.plan
        mujoco.mj_resetData(model, data)
        data.qpos[:] = plan.init_qpos
        data.qvel[:] = plan.init_qvel
        data.ctrl[:] = plan.init_ctrl
        slot.events = slot.compiled.events.start(data) if slot.compiled.events else None
        slot.actors = [actor.start(data) for actor in slot.compiled.actors]
        mujoco.mj_forward(model, data)
        slot.memory = init_memory(np, slot.compiled.program.layout, 1)
        slot.step, slot.done, slot.end_reason, slot.success, slot.score, slot.clipped_total = 0, False, None, False, 0.0, 0
        slot.stage_step = np.full(len(slot.compiled.program.layout.stages), -1, np.int32)
        slot.terms = {}

    def reset(self, env_ids: Sequence[int] | None = None, plans: Sequence[Any] | None = None) -> list[Observation]:
        ids = resolve_ids(env_ids, self.num_envs)
        if plans is not None:
            if len(plans) != ids.size:
                raise ValueError(f"reset got {len(plans)} plans for {ids.size} env_ids")
            others = [self._slots[i].plan for i in range(self.num_envs) if i not in set(ids.tolist())]
            self._check_embodiment([*others, *plans])
            for i, plan in zip(ids, plans):
                slot = self._slots[i]
                compiled = self._compile(plan)
                if compiled is not slot.compiled:
                    slot.compiled, slot.data, slot.kinematics = compiled, mujoco.MjData(compiled.model), None
                slot.plan = plan
        for i in ids:
            self._restart(self._slots[i])
        return [self._observation(self._slots[i]) for i in ids]

    # ---- stepping ----

    def step(self, actions: np.ndarray, env_ids: Sequence[int] | None = None, mode: str = "joint",
             observe: Sequence[int] | None = None) -> StepResult:
        ids = resolve_ids(env_ids, self.num_envs)
        slots = [self._slots[i] for i in ids]
        refuse_ended(ids, slots)
        if not slots:
            return self._result(ids, [], np.zeros(0, np.int32), observe)
        actions = checked_actions(actions, mode, ids.size, slots[0].compiled.robot.limits.joints_per_arm)
        bad = A.nonfinite(np, actions)
        ctrl, ee_goal, clipped = self._controls(slots, actions, mode)

        def advance(k: int) -> None:
            if bad[k]:
                return
            slot = slots[k]
            if ee_goal is not None:
                ctrl[k] = self._solve_ik(slot, ee_goal[0][k], ee_goal[1][k], ee_goal[2][k])
            slot.data.ctrl[slot.compiled.robot.actuators] = ctrl[k]
            if slot.events is not None:
                slot.compiled.events.hold(slot.events, slot.data)
            for actor, state in zip(slot.compiled.actors, slot.actors):
                actor.hold(state, slot.data, slot.step)
            if slot.events is not None and slot.events.locked:
                # a locked joint is held at every physics step, so that nothing pushing it (a key turned in a
                # locked cylinder) moves it within a control step either
                for _ in range(slot.plan.n_substeps):
                    mujoco.mj_step(slot.compiled.model, slot.data)
                    slot.compiled.events.hold_locked(slot.events, slot.data)
            else:
                mujoco.mj_step(slot.compiled.model, slot.data, nstep=slot.plan.n_substeps)

        chunks = [range(t, len(slots), self.num_threads) for t in range(min(self.num_threads, len(slots)))]
        helpers = [self._pool.submit(lambda chunk=chunk: [advance(k) for k in chunk]) for chunk in chunks[1:]]
        for k in chunks[0]:
            advance(k)
        for helper in helpers:
            helper.result()
        stepped = []
        for k, slot in enumerate(slots):
            slot.clipped_total += int(clipped[k])
            if bad[k]:
                slot.done, slot.end_reason, slot.success = True, END_NONFINITE, False
                continue
            slot.step += 1
            if any(slot.data.warning[w].number for w in DIVERGED):
                # MuJoCo has already reset the state to the model's defaults: nothing left to evaluate.
                slot.done, slot.end_reason, slot.success = True, END_UNSTABLE, False
                continue
            stepped.append(slot)
        self._evaluate(stepped)
        return self._result(ids, slots, clipped, observe)

    def _controls(self, slots: list[_Slot], actions: np.ndarray, mode: str
                  ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray] | None, np.ndarray]:
        """Actuator controls [n, 2(J+1)] for joint modes; for ee modes the IK goals (base-frame positions,
        rotations, grippers) that the workers turn into controls. Plus clipped counts [n]."""
        robot = slots[0].compiled.robot
        limits = robot.limits
        if mode in ("joint", "delta_joint"):
            q_now = np.stack([s.compiled.robot.arm_q(s.data) for s in slots])
            q, grip, clipped = A.joint_targets(np, actions, q_now, limits, delta=mode == "delta_joint")
            return A.to_ctrl(np, q, grip, limits.max_width), None, clipped
        poses = [s.compiled.robot.ee_pose(s.data) for s in slots]
        pos_now = np.stack([p for p, _ in poses])
        quat_now = np.stack([robot.ee_quat(r) for _, r in poses])
        pos, rot, grip, clipped = A.ee_targets(np, actions, pos_now, quat_now, limits, delta=mode == "delta_ee")
        ctrl = np.zeros((len(slots), 2 * (limits.joints_per_arm + 1)))
        return ctrl, (pos, rot, grip), clipped

    def _solve_ik(self, slot: _Slot, pos: np.ndarray, rot: np.ndarray, grip: np.ndarray) -> np.ndarray:
        """Controls [2(J+1)] reaching the ee goal of one slot, by DLS IK from its current joints."""
        robot = slot.compiled.robot
        if slot.kinematics is None:
            slot.kinematics = ArmKinematics(slot.compiled.model, robot)
        slot.kinematics.sync(slot.data)
        q = A.solve_ik(np, slot.kinematics, robot.arm_q(slot.data), pos, rot, robot.limits.joint_lo,
                       robot.limits.joint_hi, tol=A.IK_TOLERANCE)
        return A.to_ctrl(np, q[None], grip[None], robot.limits.max_width)[0]

    def _evaluate(self, slots: list[_Slot]) -> None:
        """Predicates of the stepped slots, one batched call per program layout; sets success, score, done."""
        groups: dict[int, list[_Slot]] = {}
        for slot in slots:
            groups.setdefault(id(slot.compiled.program.layout), []).append(slot)
        for group in groups.values():
            layout = group[0].compiled.program.layout
            states = [mujoco_state(s.compiled.program.index, s.compiled.program.params["const_pos"], s.data)
                      for s in group]
            state = {k: np.concatenate([st[k] for st in states]) for k in states[0]}
            params = {k: np.concatenate([s.compiled.params[k] for s in group]) for k in group[0].compiled.params}
            memory = {k: np.concatenate([s.memory[k] for s in group]) for k in group[0].memory}
            steps = np.asarray([s.step for s in group], dtype=np.int32)
            memory, out = program_step(np, layout, state, params, memory, steps)
            for k, slot in enumerate(group):
                slot.memory = {name: value[k:k + 1] for name, value in memory.items()}
                slot.success, slot.score = bool(out.success[k]), float(out.score[k])
                slot.stage_step = out.stage_step[k]
                slot.terms = dict(zip(layout.term_names, map(bool, out.terms[k])))
                if slot.events is not None and slot.compiled.events.fire(slot.events, slot.data, slot.step,
                                                                         out.triggers[k]):
                    mujoco.mj_forward(slot.compiled.model, slot.data)
                slot.end_reason = end_after_step(slot.success, slot.step, slot.plan.horizon)
                slot.done = slot.end_reason is not None

    # ---- observations and results ----

    def _observation(self, slot: _Slot, images: bool = True) -> Observation:
        plan = slot.plan
        obs = envelope(plan, slot.step, slot.compiled.robot.proprioception(slot.data))
        if self.privileged:
            obs["privileged"] = {"qpos": slot.data.qpos.copy(), "qvel": slot.data.qvel.copy(),
                                 "plan_hash": plan.hash, "plan_path": self.plan_paths.get(plan.hash)}
        if self.cameras and images:
            if self._renderers is None:
                from dojo.backends.mujoco.render import RendererCache

                self._renderers = RendererCache(self.width, self.height)
            frames = self._renderers.render(slot.compiled.model, slot.data, list(self.cameras), self.depth)
            obs["images"] = {c: frames[c] for c in self.cameras}
            if self.depth:
                obs["depth"] = {c: frames[f"{c}_depth"] for c in self.cameras}
        return obs

    def _result(self, ids: np.ndarray, slots: list[_Slot], clipped: np.ndarray,
                observe: Sequence[int] | None = None) -> StepResult:
        wanted = set() if observe is None else {int(i) for i in observe}

        def times(slot: _Slot) -> dict[str, int | None]:
            names = slot.compiled.program.layout.stage_names
            return {n: (int(t) if t >= 0 else None) for n, t in zip(names, slot.stage_step)}

        return StepResult(
            env_ids=ids,
            obs=[self._observation(s, observe is None or int(i) in wanted) for i, s in zip(ids, slots)],
            success=np.asarray([s.success for s in slots], dtype=bool),
            score=np.asarray([s.score for s in slots], dtype=np.float32),
            done=np.asarray([s.done for s in slots], dtype=bool),
            steps=np.asarray([s.step for s in slots], dtype=np.int32),
            stage_times=[times(s) for s in slots],
            end_reason=[s.end_reason for s in slots],
            clipped=np.asarray(clipped, dtype=np.int32),
            clipped_total=np.asarray([s.clipped_total for s in slots], dtype=np.int32),
            terms=[dict(s.terms) for s in slots],
        )

    def close(self) -> None:
        self._pool.shutdown(wait=True)
        self._prefetcher.shutdown(wait=True, cancel_futures=True)
        if self._renderers is not None:
            self._renderers.close()


def _build(plan: Any) -> _Compiled:
    """Model, predicate program and robot index of one plan (no shared state: safe in a background thread)."""
    model = plan.model()
    program = compile_program(plan, model)
    return _Compiled(model, program, RobotIndex.build(model, plan.robot),
                     {k: v[None] for k, v in program.params.items()}, compile_events(plan, model),
                     compile_actors(plan, model))
