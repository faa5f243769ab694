"""Reference policies (``zero``, ``random``, ``replay``) and the loader that turns ``policy=...`` into a Model.

They are served like any other policy, so they double as baselines (a zero policy must not solve a task) and
as fixtures for the checker, the bench and the runtime's tests.

``zero`` and ``random`` are array arithmetic on the robot's own joint state, so in joint mode they also offer that
rule as array code (``device_rule``: ``HoldRule``, ``JitterRule``), written over an array module ``xp`` (numpy or
jax.numpy, the way ``dojo.backends.actions`` is): a batched simulator runs it beside its physics (the mjx backend,
inside its tick) instead of sending every observation out and every action back. Nothing here imports a
simulator or JAX; the simulator brings ``xp`` and the uniform numbers.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from xpolicylab.embodiments import ACTION_MODES, Embodiment, get_embodiment
from xpolicylab.model import Model, Observation, PolicyMetadata, as_model


@dataclass(frozen=True)
class HoldRule:
    """``zero``'s joint-mode rule: every row of a chunk is the joint pose observed when the chunk started.

    The protocol of a chunk rule (what a simulator running it reads): a chunk has ``chunk_size`` rows and starts
    from the observed ``joint_pos`` (14 wide: arm joints and gripper opening per arm); its row r is ``row(xp,
    pose, uniform)``, where ``uniform`` holds ``draws`` fresh uniform [0, 1) numbers for that row from a generator
    seeded with ``seed``. ``matches_host``: running it gives the numbers the policy's own ``get_action_batch``
    gives, so a run's results do not depend on where it ran.
    """

    chunk_size: int
    draws: ClassVar[int] = 0
    seed: ClassVar[int] = 0
    matches_host: ClassVar[bool] = True

    def row(self, xp: Any, pose: Any, uniform: Any) -> Any:
        """The held pose itself (``pose`` [..., 14]; ``uniform`` is empty)."""
        return pose


@dataclass(frozen=True)
class JitterRule:
    """``random``'s joint-mode rule (see ``HoldRule`` for the protocol): the held pose plus uniform noise in
    [-max_delta, max_delta] per value, clipped to the embodiment's joint bounds ``lo``, ``hi``, and each gripper
    uniform in [0, 1], from ``len(lo) + 2`` draws per row. Not ``matches_host``: a simulator draws from its own
    generator (JAX's, from ``seed``), which cannot repeat numpy's stream, so its numbers differ from the host's
    while being as reproducible."""

    chunk_size: int
    seed: int
    max_delta: float
    lo: tuple[float, ...]
    hi: tuple[float, ...]
    matches_host: ClassVar[bool] = False

    @property
    def draws(self) -> int:
        return len(self.lo) + 2

    def row(self, xp: Any, pose: Any, uniform: Any) -> Any:
        """``pose`` [..., D] and ``uniform`` [..., D + 2] -> actions [..., D]. The noise is ``-max_delta + 2
        max_delta u`` computed in the draws' precision, which is how numpy's ``uniform(-max_delta, max_delta)``
        computes it: the host policy gives the same numbers when it passes its own draws."""
        d = pose.shape[-1]
        noise = (-self.max_delta + (2 * self.max_delta) * uniform[..., :d]).astype(pose.dtype)
        moved = xp.clip(pose + noise, xp.asarray(self.lo, pose.dtype), xp.asarray(self.hi, pose.dtype))
        arms = xp.reshape(moved, moved.shape[:-1] + (2, d // 2))  # per arm: joints, then its gripper
        grips = uniform[..., d:].astype(pose.dtype)
        return xp.reshape(xp.concatenate([arms[..., :-1], grips[..., None]], axis=-1), moved.shape)


class _ReferencePolicy(Model):
    """Shared configuration: ``embodiment``, ``action_mode`` (joint|ee), ``chunk_size``; ``cameras``, ``width`` and
    ``height``: the images the policy asks for (none by default). The reference policies never look at images;
    asking for them makes the evaluator render and send them, which is what a test of that path needs."""

    policy_name = "reference"
    borrows_observations = True  # what they keep, the poses, are copies

    def __init__(self, config: dict[str, Any] | None = None) -> None:
        super().__init__(config)
        self.embodiment: Embodiment = get_embodiment(str(self.config.get("embodiment", "arx_x5_bimanual")))
        self.action_mode = str(self.config.get("action_mode", "joint"))
        if self.action_mode not in ACTION_MODES:
            raise ValueError(f"action_mode must be one of {ACTION_MODES}, got {self.action_mode!r}")
        self.chunk_size = int(self.config.get("chunk_size", 8))
        if self.chunk_size < 1:
            raise ValueError("chunk_size must be at least 1")
        self.cameras = tuple(str(c) for c in self.config.get("cameras") or ())
        self.image_size = tuple(None if v is None else int(v) for v in (self.config.get("width"),
                                                                           self.config.get("height")))
        if any(v is not None and v < 1 for v in self.image_size):
            raise ValueError(f"width and height must be positive, got {self.image_size}")
        self._pose: dict[Hashable, np.ndarray] = {}  # per environment, the pose its last observation showed

    @property
    def metadata(self) -> PolicyMetadata:
        return PolicyMetadata(name=self.policy_name, action_mode=self.action_mode, chunk_size=self.chunk_size,
                              action_dim=self.embodiment.action_dim(self.action_mode),
                              embodiment=self.embodiment.name, cameras=self.cameras,
                              image_width=self.image_size[0], image_height=self.image_size[1],
                              batch=True)

    def current_pose(self, obs: Observation) -> np.ndarray:
        """The pose an action in ``action_mode`` would hold: joint_pos[14], or per arm ee_pose + gripper[16]."""
        return self.current_poses(obs["state"], 1)[0]

    def current_poses(self, state: dict[str, Any], count: int) -> np.ndarray:
        """``current_pose`` of ``count`` environments at once, from their state stacked (a columnar batch's
        ``state``), as a new float32 array ``[count, D]``: the reference policies read nothing else, and keep no
        array they were given."""
        if self.action_mode == "joint":
            return np.array(state["joint_pos"], dtype=np.float32).reshape(count, -1)
        ee = np.asarray(state["ee_pose"], dtype=np.float32).reshape(count, 2, 7)
        grip = np.asarray(state["gripper"], dtype=np.float32).reshape(count, 2, 1)
        return np.concatenate([ee, grip], axis=2).reshape(count, -1)

    def reset(self) -> None:
        self._pose.clear()

    def reset_batch(self, env_ids: Sequence[Hashable]) -> None:
        for env_id in env_ids:
            self._pose.pop(env_id, None)

    def update_obs(self, obs: Observation) -> None:
        self._pose[None] = self.current_pose(obs)

    def get_action(self) -> np.ndarray:
        return self.get_action_batch([None])[0]

    def update_obs_batch(self, obs_list: Sequence[Observation], env_ids: Sequence[Hashable]) -> None:
        self._pose.update(zip(env_ids, (self.current_pose(o) for o in obs_list), strict=True))

    def update_obs_columns(self, columns: dict[str, Any], env_ids: Sequence[Hashable]) -> None:
        """The batch's poses in one array operation (the images are never looked at)."""
        self._pose.update(zip(env_ids, self.current_poses(columns["state"], len(env_ids)), strict=True))

    def poses(self, env_ids: Sequence[Hashable]) -> np.ndarray:
        """The held poses of ``env_ids``, ``[B, D]``."""
        return np.stack([self._pose[e] for e in env_ids])


class ZeroPolicy(_ReferencePolicy):
    """Holds the current pose: every row of the chunk repeats the observed state."""

    policy_name = "zero"

    def device_rule(self) -> HoldRule | None:
        """The rule as array code (module docstring), in joint mode only."""
        return HoldRule(self.chunk_size) if self.action_mode == "joint" else None

    def get_action_batch(self, env_ids: Sequence[Hashable]) -> np.ndarray:
        poses = self.poses(env_ids)
        return np.repeat(poses[:, None, :], self.chunk_size, axis=1)


class RandomPolicy(_ReferencePolicy):
    """Bounded random motion around the current pose, reproducible from ``seed``.

    Joint mode moves each joint by at most ``max_delta`` (rad, default 0.05) and clips to the joint limits;
    ee mode moves positions by at most ``max_delta`` metres and keeps orientation. Grippers are uniform 0..1.
    """

    policy_name = "random"

    def __init__(self, config: dict[str, Any] | None = None) -> None:
        super().__init__(config)
        self.seed = int(self.config.get("seed", 0))
        self.max_delta = float(self.config.get("max_delta", 0.05))
        self.rng = np.random.default_rng(self.seed)

    def reset(self) -> None:
        super().reset()
        self.rng = np.random.default_rng(self.seed)

    def device_rule(self) -> JitterRule | None:
        """The rule as array code (module docstring), in joint mode only: the ee mode's noise moves positions in
        the end-effector frame, which only the host path knows how to do."""
        if self.action_mode != "joint":
            return None
        lo, hi = self.embodiment.joint_bounds()
        return JitterRule(self.chunk_size, self.seed, self.max_delta, tuple(map(float, lo)), tuple(map(float, hi)))

    def get_action_batch(self, env_ids: Sequence[Hashable]) -> np.ndarray:
        poses = self.poses(env_ids)
        b, d, k = poses.shape[0], poses.shape[1], self.chunk_size
        out = np.repeat(poses[:, None, :], k, axis=1)
        if self.action_mode == "joint":  # the noise first, then the grippers: numpy's stream as it always was
            uniform = np.concatenate([self.rng.random((b, k, d)), self.rng.random((b, k, 2))], axis=-1)
            return self.device_rule().row(np, out, uniform)
        for arm in range(2):
            base = 8 * arm
            out[:, :, base:base + 3] += self.rng.uniform(-self.max_delta, self.max_delta, (b, k, 3))
        out[:, :, [7, 15]] = self.rng.uniform(0.0, 1.0, size=(b, k, 2))
        return out.astype(np.float32)


class ReplayPolicy(_ReferencePolicy):
    """Plays a recorded episode back chunk by chunk, one cursor per environment.

    ``episode`` names an ``.npz`` with ``actions: float32[T, D]`` and optionally ``action_mode`` and
    ``embodiment`` (see ``save_episode``). Past the end it holds the last recorded action.
    """

    policy_name = "replay"

    def __init__(self, config: dict[str, Any] | None = None) -> None:
        config = dict(config or {})
        if "episode" not in config:
            raise ValueError("the replay policy needs episode=PATH.npz (a file written by save_episode)")
        with np.load(str(config["episode"])) as data:
            self.actions = np.asarray(data["actions"], dtype=np.float32)
            config.setdefault("action_mode", str(data["action_mode"]) if "action_mode" in data else "joint")
            if "embodiment" in data:
                config.setdefault("embodiment", str(data["embodiment"]))
        super().__init__(config)
        expected = self.embodiment.action_dim(self.action_mode)
        if self.actions.ndim != 2 or self.actions.shape[1] != expected or len(self.actions) == 0:
            raise ValueError(f"episode actions must be [T>0, {expected}], got {list(self.actions.shape)}")
        self._cursor: dict[Hashable, int] = {}

    def reset(self) -> None:
        super().reset()
        self._cursor.clear()

    def reset_batch(self, env_ids: Sequence[Hashable]) -> None:
        super().reset_batch(env_ids)
        for env_id in env_ids:
            self._cursor.pop(env_id, None)

    # It plays its recording back whatever it observes: observations are not read, not even for a pose.
    def update_obs(self, obs: Observation) -> None:
        pass

    def update_obs_batch(self, obs_list: Sequence[Observation], env_ids: Sequence[Hashable]) -> None:
        pass

    def update_obs_columns(self, columns: dict[str, Any], env_ids: Sequence[Hashable]) -> None:
        pass

    def get_action_batch(self, env_ids: Sequence[Hashable]) -> np.ndarray:
        chunks = []
        last = len(self.actions) - 1
        for env_id in env_ids:
            start = self._cursor.get(env_id, 0)
            rows = np.minimum(np.arange(start, start + self.chunk_size), last)
            chunks.append(self.actions[rows])
            self._cursor[env_id] = start + self.chunk_size
        return np.stack(chunks)


def save_episode(path: str | Path, actions: np.ndarray, action_mode: str = "joint",
                 embodiment: str = "arx_x5_bimanual") -> None:
    """Write an episode in the format the replay policy reads."""
    np.savez(str(path), actions=np.asarray(actions, dtype=np.float32), action_mode=np.array(action_mode),
             embodiment=np.array(embodiment))


BUILTIN: dict[str, type[Model]] = {"zero": ZeroPolicy, "random": RandomPolicy, "replay": ReplayPolicy}


def _class_from_file(path: Path) -> type:
    module_name = f"xpolicylab_user_{abs(hash(str(path.resolve())))}"
    spec = importlib.util.spec_from_file_location(module_name, path)
    if spec is None or spec.loader is None:
        raise ValueError(f"cannot import {path}")
    module = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(path.parent))  # let a policy package import its own sibling modules
    sys.modules[module_name] = module
    spec.loader.exec_module(module)
    if not hasattr(module, "Model"):
        raise ValueError(f"{path} defines no class named Model")
    return module.Model


def resolve_policy(spec: str) -> type:
    """``zero|random|replay``, ``package.module:Class``, a ``model.py`` file, or a folder holding one."""
    if spec in BUILTIN:
        return BUILTIN[spec]
    path = Path(spec)
    if path.is_dir() and (path / "model.py").is_file():
        return _class_from_file(path / "model.py")
    if path.suffix == ".py" and path.is_file():
        return _class_from_file(path)
    if ":" in spec:
        module_name, _, attr = spec.partition(":")
        return getattr(importlib.import_module(module_name), attr)
    raise ValueError(f"unknown policy {spec!r}: use one of {sorted(BUILTIN)}, module:Class, or a path to model.py")


def load_policy(spec: str, config: dict[str, Any] | None = None) -> Model:
    """Instantiate the policy named by ``spec`` with its configuration dict (XPolicyLab's convention: one dict).

    Classes that do not derive from ``Model`` but have ``update_obs``/``get_action`` are adapted.
    """
    return as_model(resolve_policy(spec)(dict(config or {})))
