"""The batched MJX backend: the `Backend` interface over `Engine`, with actions, predicates and proprioception
computed on the device inside the one jitted tick.

Slots and rows. `load(plans)` groups the plans into buckets (`make_buckets`, over every plan the backend knows:
those given to `preload` and to `load`; read from `bucket_cache` where a run bucketed the same plans before) and
gives each bucket one row per slot that starts in it. A slot is a (bucket, row) pair; refilling it with a plan of
the same bucket only changes the row's member index, and with a plan of another bucket it moves to a row of that
bucket that no slot uses. Neither recompiles. A plan the backend has never seen, or a bucket without a free row, is
an error that names the fix (`preload` the queue).

Per tick and bucket, traced once: actions in every mode (a per-env mode id picks `joint`, `delta_joint`, `ee` or
`delta_ee`, so one program serves all four) become actuator controls with `dojo.backends.actions`; the ee modes
solve the same damped-least-squares IK as the CPU backend, batched on the device with MJX kinematics and
Jacobians (`IK_ITERATIONS` steps in a `fori_loop`, skipped by a `cond` when no env of the bucket asks for ee);
physics sub-steps; kinematics and tendons (`_DeviceHooks.refresh`); the predicate state (`gather_state`)
and the program (`program_step`) with the plans' params gathered by member, once per lane of the bucket (one lane
per task; a bucket merged across tasks, `merge=True`, has several, see `lanes`); proprioception as in the CPU
backend's `RobotIndex.proprioception`.

A policy in the tick (`attach_rule`, then `step_with_rule`). A policy whose rule is array arithmetic on the robot's
joint state (the built-in `zero` and `random`, xpolicylab's `HoldRule` and `JitterRule`) runs in `_DeviceHooks.act`:
its chunk state (the pose the last tick observed, the pose the current chunk holds, the rows taken since the reset)
is per-env carried state beside the predicate memory, re-initialised on reset as `policy.reset` starts a fresh chunk
on the host, and each tick's actions come from it. No action crosses to the device and no observation back: a step
fetches only what a result row needs (`RESULT_OUTPUTS`). Random draws come from JAX's generator keyed by the rule's
seed, the episode's plan and its step, so an episode's draws do not depend on its slot, the batch or the order.

Implementations. `impl='warp'` (MuJoCo Warp: an NVIDIA GPU with mujoco-warp installed) is what `auto` chooses
where it can run (`cache.choose_impl`), `impl='jax'` elsewhere; the backend logs which. The two keep contacts
differently: `jax` has fixed rows per environment (`Data.contact`), Warp one pool for the whole batch whose rows
carry their world (`contact__geom`, `contact__dist`, `contact__worldid`, filled up to `nacon`), which
`pool_contact_matrix` sorts into per-environment contacts. The ee modes' IK reads only joint positions and runs
MJX's `jax` kinematics under either implementation.
"""

from __future__ import annotations

import gc
import hashlib
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from dojo.backends import actions as A
from dojo.backends.base import (Backend, ChunkRule, HostBuffers, Observation, StepResult, checked_actions, envelope,
                                resolve_ids)
from dojo.backends.held_interrupt import interrupts_held
from dojo.backends.mujoco.kinematics import RobotIndex
from dojo.backends.predicate_program import init_memory, program_step
from dojo.backends.predicate_state import gather_state
from dojo.backends.predicates import pool_contact_matrix
from dojo.backends.program_types import ProgramLayout
from dojo.backends.rotations import mat_to_quat
from dojo.backends.mjx.batch import BucketArrays, Engine, EngineGroups, Hooks, Tree, make_engine
from dojo.backends.mjx.bucket import Bucket
from dojo.backends.mjx.bucket_cache import cached_buckets
from dojo.backends.mjx.cache import (DEFAULT_GRAPH_MODE, choose_impl, choose_streams, describe_impl,
                                     enable_compilation_cache, graph_mode_name, warp_installed)
from dojo.backends.mjx.cache import graph_mode as graph_mode_of
from dojo.backends.mjx.device_cameras import BucketCameras
from dojo.backends.mjx.kernel_cache import cached_binaries, kernel_cache_dir
from dojo.backends.mjx.lanes import BucketPrograms, bucket_programs, select_lanes
from dojo.backends.mjx.merge_groups import choose_merge, task_groups
from dojo.backends.mjx.observations import StepObservations
from dojo.backends.mjx.render import CpuRenderer, RenderConfig, observation_images
from dojo.backends.mjx.sharding import Placement, local_devices
from dojo.backends.mjx.slots import FREE, SlotTable, bucket_rows

log = logging.getLogger(__name__)


MODES = ("joint", "delta_joint", "ee", "delta_ee")
JOINT, DELTA_JOINT, EE, DELTA_EE = (MODES.index(m) for m in MODES)  # ids the tick compares
"""Action modes by the id the tick receives per env."""
INPUT_WIDTH = 2 * A.EE_PER_ARM
"""Action rows are padded to the widest mode's width, so one compiled tick takes every mode."""
RESULT_OUTPUTS = ("success", "score", "stage_step", "terms", "clipped", "nonfinite")
"""The tick's outputs a step with a rule in the tick fetches: a result row's, without the proprioception."""
ROBOT_STATE = ("joint_pos", "joint_vel", "ee_pose", "gripper")
"""The tick's outputs an observation's `state` holds (float32, one row per environment)."""


class _DeviceHooks(Hooks):
    """Actions, predicates and proprioception inside the tick, and with a rule the policy (see module docstring)."""

    def __init__(self, programs: dict[str, BucketPrograms], robots: dict[str, RobotIndex], impl: str,
                 ik: bool = True, rule: ChunkRule | None = None, plans: dict[str, np.ndarray] | None = None):
        """`ik`: trace the ee modes' batched IK (`_ee_targets`). Without it the tick takes joint modes only: the IK
        is most of the tick's XLA program under `warp` (one bucket of stack_blocks: 668k of the ~750k characters
        that control and observe lower to, 9.4 s of the 11 s they take to compile on a CPU).
        `rule`: the policy run in `act` (`MjxBackend.attach_rule`); `plans`: per bucket, one uint32 per member
        naming its plan (`_plan_word`), which keys the rule's draws."""
        self.programs, self.robots, self.impl, self.ik = programs, robots, impl, ik
        self.rule, self.plans = rule, plans or {}

    def refresh(self, m: Tree, d: Tree) -> Tree:
        """What the predicates and proprioception read, at the state the sub-steps reached: body and site poses
        (kinematics), tendon lengths and speeds (the grippers). Contacts stay those the last sub-step found, as
        the CPU backend reads them after `mj_step`. A full `mjx.forward` here (collision, constraints, solver)
        was a second copy of the physics in the traced tick: 44% of the `jax` tick's program on a real plan, and
        minutes of XLA compilation on a CPU. Under `warp` the forward is one Warp call, cheap to compile."""
        if self.impl == "warp":
            return mjx.forward(m, d)
        d = mjx.tendon(m, mjx.kinematics(m, d))
        return d.tree_replace({"_impl.ten_velocity": d._impl.ten_J @ d.qvel})

    def init_extra(self, arr: BucketArrays) -> Tree:
        """One predicate memory per lane of the bucket (`lanes`), each for the whole batch, and with a rule its
        chunk state (`_chunk_state`)."""
        memories = tuple(init_memory(jnp, lane.layout, arr.size) for lane in self.programs[arr.bucket.key].lanes)
        if self.rule is None:
            return memories, ()
        joints = self.robots[arr.bucket.key].limits.joints_per_arm
        return memories, _chunk_state(arr.size, A.action_dim("joint", joints))

    def act(self, arr: BucketArrays, extra: Tree, member: jax.Array, inputs: Tree, stepping: jax.Array
            ) -> tuple[Tree, Tree]:
        """With a rule, every env's joint action is row `t mod chunk_size` of its chunk, a chunk holding the pose
        the last tick observed from its first row on; an env takes a row only when it steps, as the host loop takes
        one per step. Without a rule, the host's inputs."""
        if self.rule is None:
            return inputs, extra
        memories, state = extra
        start = state["t"] % self.rule.chunk_size == 0
        held = jnp.where(start[:, None], state["pose"], state["held"])
        row = self.rule.row(jnp, held, self._uniform(arr, member, state["t"]))
        actions = jnp.zeros((row.shape[0], INPUT_WIDTH), row.dtype).at[:, :row.shape[1]].set(row)
        state = {"pose": state["pose"], "held": held, "t": state["t"] + stepping.astype(jnp.int32),
                 "nonfinite": A.nonfinite(jnp, row)}
        return (actions, jnp.full(row.shape[0], JOINT, jnp.int32)), (memories, state)

    def _uniform(self, arr: BucketArrays, member: jax.Array, t: jax.Array) -> jax.Array:
        """Each env's `rule.draws` uniform [0, 1) numbers for row `t` of its episode, from JAX's generator keyed by
        the rule's seed, the episode's plan and t: an episode's draws depend on nothing else."""
        if not self.rule.draws:
            return jnp.zeros((member.shape[0], 0), jnp.float32)
        base = jax.random.key(self.rule.seed)
        plans = jnp.asarray(self.plans[arr.bucket.key])[member]

        def draw(plan: jax.Array, row: jax.Array) -> jax.Array:
            key = jax.random.fold_in(jax.random.fold_in(base, plan), row)
            return jax.random.uniform(key, (self.rule.draws,), jnp.float32)

        return jax.vmap(draw)(plans, t)

    def control(self, arr: BucketArrays, m: Tree, data: Tree, inputs: Tree) -> tuple[jax.Array, Tree]:
        actions, mode = inputs
        robot = self.robots[arr.bucket.key]
        q_arm = data.qpos[:, robot.qpos_adr]
        joint_dim = A.action_dim("joint", robot.limits.joints_per_arm)
        q_now = jnp.where((mode == DELTA_JOINT)[:, None, None], q_arm, 0.0)  # absolute rows add 0
        q, grip, clipped = A.joint_targets(jnp, actions[:, :joint_dim], q_now, robot.limits, delta=True)
        if self.ik:
            is_ee = (mode == EE) | (mode == DELTA_EE)
            q_ee, grip_ee, clipped_ee = jax.lax.cond(
                jnp.any(is_ee), lambda: _ee_targets(arr, robot, m, data, actions, mode == DELTA_EE, self.impl),
                lambda: (q, grip, clipped))
            q = jnp.where(is_ee[:, None, None], q_ee, q)
            grip = jnp.where(is_ee[:, None], grip_ee, grip)
            clipped = jnp.where(is_ee, clipped_ee, clipped)
        ctrl = data.ctrl.at[:, robot.actuators].set(A.to_ctrl(jnp, q, grip, robot.limits.max_width))
        return ctrl, clipped

    def observe(self, arr: BucketArrays, m: Tree, data: Tree, extra: Tree, member: jax.Array, reset: jax.Array,
                stepping: jax.Array, clipped: Tree, steps: jax.Array) -> tuple[Tree, Tree]:
        """The predicates' new memories and outputs, and the proprioception; with a rule, its state's `pose` is
        what this tick observed (the next chunk starts from it) and `nonfinite` goes out for the host to end those
        episodes as `step` does."""
        programs, robot = self.programs[arr.bucket.key], self.robots[arr.bucket.key]
        memory, chunk = extra
        if self.impl == "warp":  # the pool is sorted into worlds below; no per-environment rows to read
            geom1 = geom2 = jnp.zeros((arr.size, 0), jnp.int32)
            dist = jnp.zeros((arr.size, 0), data.qpos.dtype)
        else:
            geom1, geom2, dist = data.contact.geom1, data.contact.geom2, data.contact.dist
        memories, outputs = [], []
        for lane, lane_memory in zip(programs.lanes, memory):  # every lane on the whole batch (see `lanes`)
            params = {k: jnp.asarray(v)[member] for k, v in lane.params.items()}
            state = gather_state(jnp, lane.index, params["const_pos"], data.xpos, data.xmat, data.site_xpos,
                                 data.site_xmat, data.qpos, geom1, geom2, dist, data.qvel)
            if self.impl == "warp":
                pool = data._impl
                state["contact"] = pool_contact_matrix(
                    jnp, jnp.asarray(lane.index.arrays["geom_atom"]), pool.contact__geom, pool.contact__dist,
                    pool.contact__worldid, pool.nacon, arr.size, lane.index.n_atoms)
            new_memory, out = program_step(jnp, lane.layout, state, params, lane_memory, steps)
            memories.append(jax.tree.map(
                lambda n, o: jnp.where(stepping.reshape((-1,) + (1,) * (o.ndim - 1)), n, o), new_memory,
                lane_memory))
            outputs.append(out)
        chosen = select_lanes(jnp, jnp.asarray(programs.member_lane)[member], outputs)
        proprioception = _proprioception(robot, data)
        if self.rule is None:
            return (tuple(memories), ()), {**chosen, "clipped": clipped, **proprioception}
        chunk = {**chunk, "pose": proprioception["joint_pos"]}
        return (tuple(memories), chunk), {**chosen, "clipped": clipped, "nonfinite": chunk["nonfinite"],
                                          **proprioception}


def _chunk_state(n: int, width: int) -> dict[str, jax.Array]:
    """A rule's per-env state as a reset leaves it: `pose`, the joint pose the last tick observed (the reset tick
    writes the episode's first); `held`, the pose the current chunk holds; `t`, rows taken since the reset (a chunk
    starts at every multiple of its size, the first at once, as the host asks a policy just reset); `nonfinite`,
    whether the last row had a NaN or an infinity."""
    return {"pose": jnp.zeros((n, width), jnp.float32), "held": jnp.zeros((n, width), jnp.float32),
            "t": jnp.zeros(n, jnp.int32), "nonfinite": jnp.zeros(n, bool)}


def _plan_word(plan_hash: str) -> int:
    """A plan's hash as the uint32 that keys a rule's draws for episodes of it (stable across runs and hosts)."""
    return int.from_bytes(hashlib.sha256(plan_hash.encode()).digest()[:4], "little")


def _jax_kinematics(arr: BucketArrays, m: Tree, qpos: jax.Array) -> tuple[Tree, Tree, Tree]:
    """A Warp batch as MJX's `jax` implementation holds it, for the IK: a `jax` model with the members' varying
    fields (the warp model's rows in the `jax` layout), data holding only the joint positions (all that kinematics
    and Jacobians read), and the model's `in_axes`. MJX's Jacobian (`mjx.jac`) is written for `jax` data."""
    model = arr.bucket.model
    kin = mjx.put_model(model, impl="jax")
    rows = {name: jnp.reshape(getattr(m, name), (qpos.shape[0],) + np.shape(getattr(kin, name)))
            for name in arr.bucket.varying if hasattr(kin, name)}
    in_axes = jax.tree.map(lambda _: None, kin).tree_replace({name: 0 for name in rows})
    empty = mjx.make_data(model, impl="jax")
    data = jax.vmap(lambda q: empty.replace(qpos=q))(qpos)
    return kin.tree_replace(rows), data, in_axes


def _ee_in_base(robot: RobotIndex, d: Tree) -> tuple[jax.Array, jax.Array]:
    """End-effector positions [..., 2, 3] and rotations [..., 2, 3, 3] in the arms' base frames (batched or one
    env), as `RobotIndex.ee_pose` computes them on the CPU."""
    base_r = d.xmat[..., robot.bases, :, :]
    world_r = d.site_xmat[..., robot.ee_sites, :, :]
    pos = jnp.einsum("...aji,...aj->...ai", base_r, d.site_xpos[..., robot.ee_sites, :] - d.xpos[..., robot.bases, :])
    return pos, jnp.swapaxes(base_r, -1, -2) @ world_r


def _ee_targets(arr: BucketArrays, robot: RobotIndex, m: Tree, data: Tree, actions: jax.Array, delta: jax.Array,
                impl: str) -> tuple[jax.Array, jax.Array, jax.Array]:
    """`ee` / `delta_ee` rows -> arm joint targets [B, 2, J] by batched DLS IK from the measured joints, grippers
    [B, 2] and clipped counts [B]; `delta` [B] marks the delta_ee rows. The IK runs on `jax` kinematics."""
    pos_now, rot_now = _ee_in_base(robot, data)
    quat_now = mat_to_quat(jnp, rot_now)
    quat_now = quat_now * jnp.where(quat_now[..., :1] < 0, -1.0, 1.0)
    absolute = A.ee_targets(jnp, actions, pos_now, quat_now, robot.limits, delta=False)
    relative = A.ee_targets(jnp, actions, pos_now, quat_now, robot.limits, delta=True)
    pos, rot, grip, clipped = (jnp.where(delta.reshape((-1,) + (1,) * (a.ndim - 1)), b, a)
                               for a, b in zip(absolute, relative))
    lo, hi = jnp.asarray(robot.limits.joint_lo), jnp.asarray(robot.limits.joint_hi)
    site_body = jnp.asarray(arr.bucket.model.site_bodyid[robot.ee_sites])

    def solve(m_env: Tree, d_env: Tree, target_pos: jax.Array, target_rot: jax.Array) -> jax.Array:
        def fk(q: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
            d = mjx.com_pos(m_env, mjx.kinematics(m_env, d_env.replace(qpos=d_env.qpos.at[robot.qpos_adr].set(q))))
            p, r = _ee_in_base(robot, d)
            base_r = d.xmat[robot.bases]
            jacs = []
            for arm in range(2):
                jacp, jacr = mjx.jac(m_env, d, d.site_xpos[robot.ee_sites[arm]], site_body[arm])
                cols = robot.dof_adr[arm]
                jacs.append(jnp.concatenate([base_r[arm].T @ jacp[cols].T, base_r[arm].T @ jacr[cols].T]))
            return p, r, jnp.stack(jacs)

        step = lambda _, q: A.ik_iteration(jnp, fk, q, target_pos, target_rot, lo, hi)[0]
        return jax.lax.fori_loop(0, A.IK_ITERATIONS, step, d_env.qpos[robot.qpos_adr])

    m_kin, d_kin, in_axes = (m, data, arr.in_axes) if impl == "jax" else _jax_kinematics(arr, m, data.qpos)
    q = jax.vmap(solve, in_axes=(in_axes, 0, 0, 0))(m_kin, d_kin, pos, rot)
    return q, grip, clipped


def _proprioception(robot: RobotIndex, d: Tree) -> dict[str, jax.Array]:
    """`RobotIndex.proprioception` for a batch of MJX data (float32, [B, ...])."""
    width = robot.limits.max_width
    grip = jnp.clip(d.ten_length[:, robot.tendons] / width, 0.0, 1.0)
    pos, rot = _ee_in_base(robot, d)
    quat = mat_to_quat(jnp, rot)
    quat = quat * jnp.where(quat[..., :1] < 0, -1.0, 1.0)
    arm_q, arm_v = d.qpos[:, robot.qpos_adr], d.qvel[:, robot.dof_adr]
    grip_v = d._impl.ten_velocity[:, robot.tendons] / width
    return {"joint_pos": jnp.concatenate([arm_q, grip[..., None]], -1).reshape(arm_q.shape[0], -1),
            "joint_vel": jnp.concatenate([arm_v, grip_v[..., None]], -1).reshape(arm_q.shape[0], -1),
            "ee_pose": jnp.concatenate([pos, quat], -1), "gripper": grip}


class MjxBackend(Backend):
    """Batched MJX backend (`impl` 'jax', 'warp' or 'auto', see the module docstring); images rendered on the
    device under `warp` (`device_cameras`), on the host under `jax`. Under `warp` every tick checks MuJoCo Warp's
    overflow bits: a dropped contact raises `CapacityOverflow` instead of scoring physics that is not the plan's."""

    name = "mjx"

    def __init__(self, impl: str | None = "jax", cache_dir: str | None = None, privileged: bool = False,
                 plan_paths: dict[str, str] | None = None, cameras: Sequence[str] = (), width: int = 640,
                 height: int = 480, depth: bool = False, devices: int | str | None = None,
                 merge: bool | str = False, merge_growth: float | None = None,
                 graph_mode: str | None = DEFAULT_GRAPH_MODE, action_modes: Sequence[str] | None = None,
                 streams: bool | str = False, program_buckets: int | None = None) -> None:
        """`privileged`: observations also carry `privileged: {qpos, qvel, plan_hash, plan_path}` in the plan's own
        layout, as the mujoco backend gives them, for privileged reference policies only (the `oracle`).
        `cameras`: the images observations carry (DESIGN section 4), only for observed slots: under `warp` by
        MuJoCo Warp's batched renderer from the engine's state on the GPU (`device_cameras.BucketCameras`), under
        `jax` from each environment's padded model and state by MuJoCo's renderer on the host (`CpuRenderer`).
        `devices`: how many local devices every bucket's environments are split over (`sharding`); all of them by
        default, so one process uses every GPU of its host.
        `merge`: buckets merged across tasks (`make_buckets(merge=True)`): tasks of one robot share a structure
        where the scenes allow it and the merged model stays within `1 + merge_growth` of its largest task's own
        (DoFs and geoms; `merge_groups.GROWTH` says why), each task's program a lane of its bucket (`lanes`). The
        same bound holds where one task's plans are padded together (`merge_groups.padding_groups`), merged or not.
        `auto`: decided at `load`, from the run's environments per task and whether the physics is on streams
        (`merge_groups.choose_merge`). `merge_growth` None: the default of what is chosen (`GROWTH`, or
        `AUTO_GROWTH` where auto merges).
        `graph_mode`: how MJX captures its Warp calls in CUDA graphs (`cache.GRAPH_MODES`, `cache.DEFAULT_GRAPH_MODE`;
        None: MJX's own default).
        `streams`: under `warp` on one GPU, every bucket's physics on its own CUDA stream between two jitted halves
        of the tick (`streams.StreamPhysics`) instead of one after another inside it; `auto`: where
        `cache.choose_streams` says.
        `program_buckets`: at most this many buckets share one jitted program (`batch.make_engine`; None:
        `batch.PROGRAM_BUCKETS`), so that a suite of many buckets compiles group by group.
        `action_modes`: the modes `step` will be given (None: all of `MODES`); the ee modes' IK is compiled only
        when one of them is among these, and `step` refuses the others."""
        self.action_modes = tuple(action_modes) if action_modes is not None else MODES
        unknown = [m for m in self.action_modes if m not in MODES]
        if unknown:
            raise ValueError(f"unknown action modes {unknown}; choose from {list(MODES)}")
        enable_compilation_cache(cache_dir)
        self.privileged, self.plan_paths = privileged, dict(plan_paths or {})
        self.render_config = RenderConfig(tuple(cameras), width, height, depth) if cameras else None
        self._renderers: list[CpuRenderer | BucketCameras] = []
        self.impl = choose_impl(impl)
        choose_merge(merge, merge_growth, False, 0, 0)  # a bad setting fails here, before any compiling
        self.merge, self.merge_growth = merge, merge_growth
        self.merged = False
        """Whether `load` merged buckets across tasks (`merge`, decided there under `auto`)."""
        self.graph_mode = graph_mode_of(graph_mode, self.impl)
        self.program_buckets = program_buckets
        log.info("mjx backend: %s%s", describe_impl(self.impl),
                 f", CUDA graphs: {graph_mode_name(self.graph_mode)}" if self.graph_mode is not None else "")
        if self.impl == "jax" and jax.default_backend() == "cpu" and warp_installed():
            # Measured on the 2-core machine (2026-11-28): push_t's tick compiled for 20 minutes under `jax`, then
            # LLVM failed ("Unable to allocate section memory"), while `warp` ran the same command to its end.
            log.warning("mjx backend: on a CPU, XLA compiles a real task's tick for tens of minutes and may fail; "
                        "backend.impl=warp runs MuJoCo Warp's kernels on the CPU instead")
        self._known: dict[str, Any] = {}
        self._slots = SlotTable([], [], [], [])
        self._engine: Engine | EngineGroups | None = None
        self._buckets: list[Bucket] = []
        self._member: dict[str, tuple[int, int]] = {}
        self._stage_layouts: dict[str, ProgramLayout] = {}  # plan hash -> its program's stage and term names
        self._members: list[np.ndarray] = []
        self._joints_per_arm = 0
        self._rule: ChunkRule | None = None
        self._image_buffers: HostBuffers | None = None
        self.placement = Placement.over(local_devices(devices), self.impl)
        log.info("mjx backend: environments split over %s", self.placement.describe())
        self.streams, why = choose_streams(streams, self.impl, self.placement.on_gpu, self.render_config is not None)
        if streams == "auto":
            log.info("mjx backend: physics %s (backend.streams=%s)",
                     "on streams, each bucket on its own" if self.streams else "in the jitted tick", why)

    @property
    def num_envs(self) -> int:
        return len(self._slots)

    def attach_rule(self, rule: ChunkRule) -> None:
        """Run `rule` as every slot's policy inside the tick (module docstring): `step_with_rule` steps with it, and
        `step` is refused. Only before `load`: the rule is traced into the tick `load` compiles, which serves the
        whole run as one program. A tick that could take either the rule's actions or the host's would need the
        host's as inputs every step, the copy a rule in the tick is there to avoid."""
        if self._engine is not None:
            raise RuntimeError("attach_rule before load: the rule is traced into the tick that load compiles")
        self._rule = rule

    def preload(self, plans: Sequence[Any]) -> None:
        """Make plans known before `load`, so that refilling slots with them later compiles nothing."""
        self._known.update({p.hash: p for p in plans})

    def load(self, plans: Sequence[Any]) -> None:
        """Start one slot per plan. Every bucket of every known plan (`preload` and these) gets rows: as many as
        its plans could ever occupy at once (its known plans, at most one per slot), so that any refill finds a
        free row in its bucket and the program compiled now serves the whole run."""
        self.preload(plans)
        if len({p.embodiment for p in self._known.values()}) > 1:
            raise ValueError("one backend runs one embodiment (action layout)")
        start = time.perf_counter()
        self.merged, growth, why = choose_merge(self.merge, self.merge_growth, self.streams, len(plans),
                                                task_groups(self._known.values()))
        if self.merge == "auto" or self.merged:
            log.info("mjx backend: buckets %s (backend.merge=%s)",
                     f"merged across tasks, growth {growth:g}" if self.merged else "not merged across tasks",
                     why if self.merge == "auto" else str(self.merge).lower())
        self._buckets, entry = cached_buckets(list(self._known.values()), self.merged, growth)
        # Set-up can take minutes (a compile per bucket structure): say where it stands before each long step.
        log.info("mjx backend: %d plan(s) in %d bucket(s), largest nv %d (%.1f s%s); building the engine",
                 len(self._known), len(self._buckets), max(b.model.nv for b in self._buckets),
                 time.perf_counter() - start, f", as bucketed before: {entry}" if entry else "")
        self._member = {m.plan.hash: (k, i) for k, b in enumerate(self._buckets) for i, m in enumerate(b.members)}
        self._stage_layouts = {}
        self._layouts = {m.plan.hash: PlanLayout.build(m.model, m.plan.model(), m.padded.names)
                         for b in self._buckets for m in b.members}
        buckets = [self._member[plan.hash][0] for plan in plans]
        rows = [0] * len(plans)
        taken = [0] * len(self._buckets)  # rows each bucket's first slots take
        for s, k in enumerate(buckets):
            rows[s], taken[k] = taken[k], taken[k] + 1
        capacity = [self.placement.padded(bucket_rows(len(plans), len(bucket.members), taken[k]))
                    for k, bucket in enumerate(self._buckets)]
        self._slots = SlotTable(plans, buckets, rows, capacity)
        self._members = [np.zeros(size, np.int32) for size in capacity]
        for s, plan in enumerate(plans):
            self._members[buckets[s]][rows[s]] = self._member[plan.hash][1]
        self._joints_per_arm = len(plans[0].robot["arm_joints"]) // 2
        hooks = _DeviceHooks({b.key: bucket_programs(b) for b in self._buckets},
                             {b.key: RobotIndex.build(b.model, b.members[0].plan.robot) for b in self._buckets},
                             self.impl, ik=any(MODES.index(m) in (EE, DELTA_EE) for m in self.action_modes),
                             rule=self._rule,
                             plans={b.key: np.asarray([_plan_word(m.plan.hash) for m in b.members], np.uint32)
                                    for b in self._buckets})
        example = self._idle_inputs()
        self.close()
        self._engine = None  # the old engine's buffers go before the new one captures (`capture`); its jitted
        gc.collect()         # tick refers back to it, so only the collector frees it
        cached = cached_binaries() if self.impl == "warp" else None
        start = time.perf_counter()
        self._engine = make_engine(self._buckets, capacity, self.impl, hooks, example, placement=self.placement,
                                   graph_mode=self.graph_mode, streams=self.streams,
                                   per_program=self.program_buckets)
        if self.render_config is not None:
            self._renderers = [BucketCameras(arr, self.render_config, self._image_buffers) if self.impl == "warp" else
                               CpuRenderer([m.model for m in arr.bucket.members], self.render_config)
                               for arr in self._engine.arrays]
        lanes = "; each bucket's physics on its own Warp lane between two jitted halves (backend.streams)"
        groups = (f"; its {len(self._buckets)} buckets in {len(self._engine.engines)} programs (backend."
                  f"program_buckets)" if isinstance(self._engine, EngineGroups) else "")
        log.info("mjx backend: engine built, its first tick compiled (%.1f s)%s%s; first tick",
                 time.perf_counter() - start, groups, lanes if self.streams else "")
        start = time.perf_counter()
        self.reset()
        log.info("mjx backend: first tick done (%.1f s)", time.perf_counter() - start)
        if cached is not None:
            self._say_compiled(len(cached_binaries() - cached))

    @staticmethod
    def _say_compiled(count: int) -> None:
        """How many Warp modules the set-up compiled on this machine rather than found in the kernel cache."""
        where = kernel_cache_dir()
        if count:
            log.info("mjx backend: Warp compiled %d module(s) here during set-up, not found in its kernel cache (%s; "
                     "`dojo bench kernels ... arch=` compiles them ahead on any machine)", count, where)
        else:
            log.info("mjx backend: Warp found every module of the set-up in its kernel cache (%s)", where)

    def _row_for(self, s: int, plan: Any) -> tuple[int, int]:
        """The bucket and row slot `s` plays `plan` in: its own row when the plan is of its bucket, else a free one."""
        if plan.hash not in self._member:
            raise ValueError(f"plan {plan.hash[:12]} ({plan.task}) was not given to preload/load; refilling with "
                             "it would need a new compilation")
        k, _ = self._member[plan.hash]
        if k == self._slots.bucket[s]:
            return k, int(self._slots.row[s])
        free = np.flatnonzero(self._slots.rows[k] == FREE)
        if not free.size:
            raise ValueError(f"no free row in bucket {self._buckets[k].key} for plan {plan.hash[:12]}: load started "
                             f"{len(self._slots.rows[k])} slots in it")
        return k, int(free[0])

    def reset(self, env_ids: Sequence[int] | None = None, plans: Sequence[Any] | None = None) -> list[Observation]:
        ids = resolve_ids(env_ids, self.num_envs)
        if plans is not None:
            if len(plans) != ids.size:
                raise ValueError(f"reset got {len(plans)} plans for {ids.size} env_ids")
            for s, plan in zip(ids.tolist(), plans):
                k, row = self._row_for(s, plan)
                self._slots.move(s, plan, k, row)
                self._members[k][row] = self._member[plan.hash][1]
        self._slots.restart(ids)
        outputs = self._tick(self._slots.flags(ids), self._slots.flags(ids[:0]), self._idle_inputs(), ids)
        return list(self._observations(ids, outputs))

    def _idle_inputs(self) -> list[Tree]:
        """Per bucket, the tick's inputs when the host sends no actions (resets): zero action rows, or nothing at
        all when a rule makes the actions in the tick."""
        if self._rule is not None:
            return [() for _ in self._slots.rows]
        return [(np.zeros((len(r), INPUT_WIDTH), np.float32), np.zeros(len(r), np.int32)) for r in self._slots.rows]

    def _tick(self, resets: list[np.ndarray], stepping: list[np.ndarray], inputs: list[Tree], ids: np.ndarray,
              names: Sequence[str] | None = None) -> list[dict[str, np.ndarray]]:
        """One engine tick; the outputs of the buckets that hold slots `ids` (the slots the caller reads) copied to
        the host, only those in `names` when given; other buckets' are left on the device ({}).

        Why not every bucket's: each output is a copy of its own, and a protocol run's tick fetched some 280 (46
        buckets, 6 outputs) whether or not a bucket still held a running episode: 62 of its 613 s of steps on an
        H200 (2026-12-03, cProfile)."""
        with interrupts_held():  # a Ctrl-C inside the tick's FFI callbacks would hang the run's exit
            out = self._engine.tick(self._members, resets, stepping, inputs, self._slots.next_steps())
            if self.impl == "warp":
                self._engine.check_overflow()
            read = set(self._slots.bucket[ids].tolist())
            return jax.device_get([(o if names is None else {n: o[n] for n in names}) if k in read else {}
                                   for k, o in enumerate(out)])

    def step(self, actions: np.ndarray, env_ids: Sequence[int] | None = None, mode: str = "joint",
             observe: Sequence[int] | None = None) -> StepResult:
        if self._rule is not None:
            raise ValueError("a policy rule is attached to this mjx backend: its tick makes the actions and takes "
                             "none from the host (step_with_rule)")
        if mode not in self.action_modes:
            raise ValueError(f"this mjx backend was built for action modes {list(self.action_modes)}, not '{mode}' "
                             "(its tick compiles only those; give the policy's mode in BackendOptions.action_modes)")
        ids = resolve_ids(env_ids, self.num_envs)
        self._slots.refuse_ended(ids)
        actions = checked_actions(actions, mode, ids.size, self._joints_per_arm)
        bad = A.nonfinite(np, actions)
        inputs = [(np.zeros((len(r), INPUT_WIDTH), np.float32), np.full(len(r), MODES.index(mode), np.int32))
                  for r in self._slots.rows]
        fine = ids[~bad]
        for k, at in self._slots.by_bucket(fine):
            inputs[k][0][self._slots.row[fine[at]], :actions.shape[1]] = actions[~bad][at]
        outputs = self._tick(self._slots.flags(ids[:0]), self._slots.flags(fine), inputs, ids)
        clipped = self._slots.advance(ids, bad, outputs, self._stage_layout)
        return self._slots.result(ids, self._observations(ids, outputs, observe=observe), clipped)

    def step_with_rule(self, env_ids: Sequence[int] | None = None) -> StepResult:
        """One control step of slots `env_ids` with the attached rule's actions (`attach_rule`), made in the tick
        from the state there. Only `RESULT_OUTPUTS` come back to the host, and the result has no observations."""
        if self._rule is None:
            raise ValueError("no policy rule is attached to this mjx backend: attach_rule before load, or step")
        ids = resolve_ids(env_ids, self.num_envs)
        self._slots.refuse_ended(ids)
        outputs = self._tick(self._slots.flags(ids[:0]), self._slots.flags(ids), self._idle_inputs(), ids,
                             names=RESULT_OUTPUTS)
        bad = np.zeros(ids.size, bool)
        for k, at in self._slots.by_bucket(ids):
            bad[at] = np.asarray(outputs[k]["nonfinite"])[self._slots.row[ids[at]]]
        return self._slots.result(ids, [], self._slots.advance(ids, bad, outputs, self._stage_layout))

    def _stage_layout(self, s: int) -> ProgramLayout:
        """The stage and term names of slot `s`'s program (looked up once per plan until the next `load`)."""
        plan = self._slots.plans[s]
        layout = self._stage_layouts.get(plan.hash)
        if layout is None:
            k, member = self._member[plan.hash]
            program = self._engine.hooks.programs[self._buckets[k].key]
            layout = self._stage_layouts[plan.hash] = program.layout_of(member)
        return layout

    def _observations(self, ids: np.ndarray, outputs: list[dict[str, np.ndarray]],
                      observe: Sequence[int] | None = None) -> StepObservations:
        """Observations of slots `ids`, each built when read (`observations`); images (when the backend has
        cameras) only for those in `observe` (all when None), rendered per bucket in one call. The state arrays
        are rows of one copy per bucket and call."""
        table = self._slots
        positions, buckets, rows = ids.tolist(), table.bucket[ids].tolist(), table.row[ids].tolist()
        observations = StepObservations(
            [table.plans[s] for s in positions], table.step[ids].tolist(), buckets, rows,
            {k: {name: np.array(outputs[k][name], np.float32) for name in ROBOT_STATE} for k, _ in table.by_bucket(ids)})
        fetched: dict[int, tuple[np.ndarray, np.ndarray | None]] = {}

        def state(bucket: int) -> tuple[np.ndarray, np.ndarray | None]:
            """One device-to-host copy of a bucket's qpos (and qvel when privileged) per call."""
            if bucket not in fetched:
                fetched[bucket] = (np.asarray(self._engine.field(bucket, "qpos"), np.float64),
                                   np.asarray(self._engine.field(bucket, "qvel"), np.float64) if self.privileged
                                   else None)
            return fetched[bucket]

        if self.render_config is not None:
            wanted = np.ones(ids.size, bool) if observe is None else np.isin(ids, np.asarray(observe, np.int64))
            for k, renderer in enumerate(self._renderers):
                picked = np.flatnonzero(wanted & (table.bucket[ids] == k))
                if not picked.size:
                    continue
                picked_rows = table.row[ids[picked]]
                if isinstance(renderer, BucketCameras):
                    frames = renderer.frames(self._engine.data[k], self._members[k], picked_rows.tolist())
                else:
                    frames = renderer.render([self._member[table.plans[s].hash][1] for s in ids[picked].tolist()],
                                             list(state(k)[0][picked_rows]))
                for at, images in zip(picked.tolist(), observation_images(frames, self.render_config.cameras)):
                    observations.add(at, images)
        if self.privileged:
            for at, (s, k, r) in enumerate(zip(positions, buckets, rows)):
                qpos, qvel = state(k)
                plan = table.plans[s]
                layout = self._layouts[plan.hash]
                observations.add(at, {"privileged": {"qpos": layout.qpos(qpos[r]), "qvel": layout.qvel(qvel[r]),
                                                     "plan_hash": plan.hash, "plan_path": self.plan_paths.get(plan.hash)}})
        return observations

    def use_image_buffers(self, buffers: HostBuffers) -> None:
        """Device cameras (`warp`) copy their images into buffers from `buffers` (`host_copy`, lent buffers)."""
        if self.impl == "warp" and self.render_config is not None:
            log.info("mjx backend: camera images are copied off the GPU into the policy link's shared memory and "
                     "sent from there")
        self._image_buffers = buffers
        for renderer in self._renderers:
            if isinstance(renderer, BucketCameras):
                renderer.use_buffers(buffers)

    def close(self) -> None:
        """Let the cameras go, and wait for the physics a tick left running (`Engine.wait_for_lanes`): the run's
        `finally` calls this, also when it was interrupted mid-tick."""
        if self._engine is not None:
            self._engine.wait_for_lanes()
            launched, idle = self._engine.lane_ticks()
            if idle:
                log.info("mjx backend: %d of %d lane ticks not launched, every environment of the lane idle",
                         idle, launched + idle)
        for renderer in self._renderers:
            renderer.close()
        self._renderers = []

    def qpos(self, env_ids: Sequence[int] | None = None) -> np.ndarray:
        """Generalised positions of slots in their plan's own layout (parked clutter slots dropped) [n, nq]."""
        ids = resolve_ids(env_ids, self.num_envs)
        table = self._slots
        qpos = {k: np.asarray(self._engine.field(k, "qpos")) for k in set(table.bucket[ids].tolist())}
        out = [self._layouts[table.plans[s].hash].qpos(qpos[table.bucket[s]][table.row[s]]) for s in ids.tolist()]
        return np.stack(out) if out else np.zeros((0, 0))


@dataclass(frozen=True)
class PlanLayout:
    """Where each joint of a padded bucket model sits in the plan's own model: index maps that move a padded
    qpos (or qvel) back into the plan's layout, for the oracle and for comparison with `mujoco`. Parked slots have
    no place there and are dropped. Built once per bucket member: the map never changes while it runs."""

    nq: int
    nv: int
    qpos_padded: np.ndarray
    qpos_plan: np.ndarray
    qvel_padded: np.ndarray
    qvel_plan: np.ndarray

    @classmethod
    def build(cls, padded: mujoco.MjModel, source: mujoco.MjModel, names: dict[str, str]) -> "PlanLayout":
        maps: dict[bool, tuple[list[int], list[int]]] = {False: ([], []), True: ([], [])}
        for j in range(padded.njnt):
            name = mujoco.mj_id2name(padded, mujoco.mjtObj.mjOBJ_JOINT, j)
            src = mujoco.mj_name2id(source, mujoco.mjtObj.mjOBJ_JOINT, names.get(name, name))
            if src < 0:
                continue
            for velocity, (pad_adr, src_adr, widths) in {
                    False: (padded.jnt_qposadr, source.jnt_qposadr, {0: 7, 1: 4}),
                    True: (padded.jnt_dofadr, source.jnt_dofadr, {0: 6, 1: 3})}.items():
                width = widths.get(int(padded.jnt_type[j]), 1)
                maps[velocity][0].extend(range(pad_adr[j], pad_adr[j] + width))
                maps[velocity][1].extend(range(src_adr[src], src_adr[src] + width))
        index = {v: tuple(np.asarray(ix, np.int64) for ix in pair) for v, pair in maps.items()}
        return cls(source.nq, source.nv, *index[False], *index[True])

    def qpos(self, values: np.ndarray) -> np.ndarray:
        out = np.zeros(self.nq)
        out[self.qpos_plan] = np.asarray(values)[self.qpos_padded]
        return out

    def qvel(self, values: np.ndarray) -> np.ndarray:
        out = np.zeros(self.nv)
        out[self.qvel_plan] = np.asarray(values)[self.qvel_padded]
        return out
