"""The one interface every backend implements, and the result of a step.

A backend holds `num_envs` environment *slots*. `load(plans)` puts plans[i] in slot i at its initial state;
`reset(env_ids, plans)` starts a fresh episode in some slots, optionally with new plans (continuous batching:
a finished slot is refilled while the others keep running); `step(actions, env_ids, mode)` advances the named
slots by one control step (`plan.n_substeps` physics steps at `plan.control_hz`) and evaluates the plan's
predicates. Everything is batched over `env_ids`, and results come back in `env_ids` order.

An episode ends (`done`) on success, at the plan's horizon, on a non-finite action, or when the physics diverged
(the simulator would otherwise silently restart the state); `end_reason` says which.
A slot whose episode ended must be reset before it is stepped again (stepping it raises `EpisodeDone`).

Observations follow DESIGN section 4 / xpolicylab: `{"instruction": str, "images": {camera: uint8[H, W, 3]}
(only the cameras the backend was asked for), "state": {"joint_pos" [14], "joint_vel" [14], "ee_pose" [2, 7],
"gripper" [2]} (float32), "meta": {"task", "episode", "step", "embodiment", "control_hz"}}`. `meta.episode` is
the plan's scene seed; the runtime, which numbers episodes, may overwrite it.

A backend that steps on a device may also run a policy itself (`attach_rule`, then `step_with_rule`): a policy
whose whole rule is array arithmetic on the robot's joint state (a `ChunkRule`) then needs no observation copied
out and no action copied back per step. Host backends do not (their package does not set `RUNS_POLICY_RULES`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol, Self

import numpy as np

from dojo.backends import actions as A

Observation = dict[str, Any]

END_SUCCESS = "success"
END_HORIZON = "horizon"
END_NONFINITE = "non_finite_action"
END_UNSTABLE = "physics_unstable"
END_REASONS = (END_SUCCESS, END_HORIZON, END_NONFINITE, END_UNSTABLE)


class EpisodeDone(RuntimeError):
    """A slot whose episode has ended was stepped without a reset."""


@dataclass
class StepResult:
    """One control step of the slots `env_ids`, every field in `env_ids` order (length n).

    `stage_times[i]` maps each stage name to the control step it was first reached (None = not yet): the
    `EpisodeResult.stage_times` of the episode. `end_reason[i]` is one of END_REASONS once `done[i]`, else
    None; an episode's `failure_reason` is its end reason unless it succeeded. `clipped[i]` counts the action
    elements clipped to limits in this step, `clipped_total[i]` in the whole episode. `terms[i]` maps each
    success term (`ProgramLayout.term_names`) to whether it holds now (empty for a backend that does not say).
    `counters[i]` holds the backend's own counts over the episode so far, by name (empty for a backend that keeps
    none; the `real` backend: its safety layer's clips and refusals), recorded with the episode.
    `obs` is any sequence: a batched backend may build each observation only when it is read (`mjx.observations`),
    since a run loop reads those of the slots it asks the policy for next, not all of them every step.
    """

    env_ids: np.ndarray
    obs: Sequence[Observation]
    success: np.ndarray
    score: np.ndarray
    done: np.ndarray
    steps: np.ndarray
    stage_times: list[dict[str, int | None]]
    end_reason: list[str | None]
    clipped: np.ndarray
    clipped_total: np.ndarray
    terms: list[dict[str, bool]] = field(default_factory=list)
    counters: list[dict[str, int]] = field(default_factory=list)


class HostBuffers(Protocol):
    """Host memory lent to a backend for camera images: buffers in the policy link's shared memory
    (`xpolicylab.shm.SegmentPool.lend`), so that images copied there from a GPU go to the policy server as they lie."""

    def lend(self, nbytes: int) -> np.ndarray:
        """A writable uint8 buffer of `nbytes`, kept until `give_back`; MemoryError when none can be had."""

    def give_back(self, buffer: np.ndarray) -> None:
        """Return a buffer from `lend` (its memory goes once nothing refers to it)."""


class ChunkRule(Protocol):
    """A policy's joint-mode rule as array code (xpolicylab's `HoldRule`, `JitterRule`): chunks of `chunk_size`
    rows, each chunk held from the `joint_pos` observed when it starts; row r of a chunk is `row(xp, pose,
    uniform)` with `uniform` `draws` fresh uniform [0, 1) numbers for that row, from a generator seeded with
    `seed`. `matches_host`: the numbers equal those the policy gives when asked on the host."""

    chunk_size: int
    draws: int
    seed: int
    matches_host: bool

    def row(self, xp: Any, pose: Any, uniform: Any) -> Any: ...


class Backend(ABC):
    """A simulator (or robot) that runs plans in `num_envs` slots. Use as a context manager or call close()."""

    name: ClassVar[str]
    max_envs: ClassVar[int | None] = None
    """The most slots the backend can hold (None: as many as asked); the evaluation loop runs no more. A robot: 1."""

    @property
    @abstractmethod
    def num_envs(self) -> int:
        """Number of slots (set by `load`)."""

    @abstractmethod
    def load(self, plans: Sequence[Any]) -> None:
        """Allocate one slot per plan (slot i runs plans[i]) and put each at its plan's initial state."""

    @abstractmethod
    def reset(self, env_ids: Sequence[int] | None = None, plans: Sequence[Any] | None = None) -> list[Observation]:
        """Start new episodes in `env_ids` (all slots when None), first replacing their plans when `plans` (one
        per id) is given. Returns their first observations."""

    @abstractmethod
    def step(self, actions: np.ndarray, env_ids: Sequence[int] | None = None, mode: str = "joint",
             observe: Sequence[int] | None = None) -> StepResult:
        """Apply actions [n, D] (one row per id, `mode` one of actions.ACTION_MODES) for one control step.
        Camera images are rendered only for the slots in `observe` (all when None): a policy executing an action
        chunk looks only when its chunk runs out, and rendering is the dominant cost on a CPU."""

    def attach_rule(self, rule: ChunkRule) -> None:
        """Run `rule` as the policy of every slot from the next `load` on (`step_with_rule`); only backends whose
        package sets `RUNS_POLICY_RULES` can."""
        raise NotImplementedError(f"backend {self.name} runs no policy rule inside its step")

    def step_with_rule(self, env_ids: Sequence[int] | None = None) -> StepResult:
        """`step` with the attached rule's actions, made where the state is: the result's `obs` is empty."""
        raise NotImplementedError(f"backend {self.name} runs no policy rule inside its step")

    def use_image_buffers(self, buffers: HostBuffers) -> None:
        """A hint: camera images may be copied into host memory from `buffers` (the policy link's shared memory),
        through which they reach a policy server on this host without another copy. Backends that copy no
        images off a device ignore it."""

    def prefetch(self, plans: Sequence[Any]) -> None:
        """A hint: these plans will be loaded soon (the runtime's next queued episodes); a backend may prepare
        them in the background. Backends with nothing to prepare ignore it."""

    def close(self) -> None:
        """Release threads, renderers and devices."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def refuse_ended(ids: np.ndarray, slots: Sequence[Any]) -> None:
    """Stepping a slot whose episode has ended is the caller's mistake (it must reset the slot first): raise
    `EpisodeDone` naming each such slot and why its episode ended (slots carry `done` and `end_reason`)."""
    ended = {int(i): s.end_reason for i, s in zip(ids, slots) if s.done}
    if ended:
        raise_ended(ended)


SHOWN_ENDED = 8
"""Slots an `EpisodeDone` lists by number: a batch of thousands that all ended would otherwise be a page of text."""


def raise_ended(ended: Mapping[int, str | None]) -> None:
    """`EpisodeDone` for stepping slots whose episodes ended: {slot: end reason}, the first `SHOWN_ENDED` named."""
    shown = dict(list(ended.items())[:SHOWN_ENDED])
    more = f" and {len(ended) - len(shown)} more" if len(ended) > len(shown) else ""
    raise EpisodeDone(f"episodes ended in {len(ended)} slot(s) {shown}{more} (slot: reason); reset them before "
                      "stepping")


def checked_actions(actions: Any, mode: str, n: int, joints_per_arm: int) -> np.ndarray:
    """`actions` as float64 [n, D] for action `mode` (D from `actions.action_dim`), or a ValueError saying the
    shape expected: every backend takes the same action rows, and says so the same way."""
    dim = A.action_dim(mode, joints_per_arm)
    actions = np.asarray(actions, dtype=np.float64)
    if actions.shape != (n, dim):
        raise ValueError(f"actions for mode {mode!r} must have shape ({n}, {dim}), got {actions.shape}")
    return actions


def envelope(plan: Any, step: int, state: dict[str, np.ndarray]) -> Observation:
    """An observation without images (module docstring): what every backend returns for a slot at `step` of
    `plan`'s episode, the robot's `state` read its own way. Images and privileged state are added to it."""
    return {"instruction": plan.instruction, "state": state,
            "meta": {"task": plan.task, "episode": plan.seed, "step": step, "embodiment": plan.embodiment,
                     "control_hz": plan.control_hz}}


def end_after_step(success: bool, step: int, horizon: int) -> str | None:
    """The end rule after a control step that was taken and evaluated: success ends the episode, else reaching
    the horizon does (None: it goes on). Non-finite actions and diverged physics end it before evaluation."""
    if success:
        return END_SUCCESS
    return END_HORIZON if step >= horizon else None


def resolve_ids(env_ids: Sequence[int] | None, num_envs: int) -> np.ndarray:
    """`env_ids` as an int array (all slots when None), checked to be distinct and in range."""
    ids = np.arange(num_envs) if env_ids is None else np.asarray(env_ids, dtype=np.int64).reshape(-1)
    if ids.size and (ids.min() < 0 or ids.max() >= num_envs):
        raise IndexError(f"env_ids {ids.tolist()} out of range for {num_envs} slots")
    if len(set(ids.tolist())) != ids.size:
        raise ValueError(f"env_ids {ids.tolist()} repeat a slot")
    return ids
