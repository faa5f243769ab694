"""Reference policies (``zero``, ``random``, ``replay``) and the loader that turns ``policy=...`` into a Model.

They are served like any other policy, so they double as baselines (a zero policy must not solve a task) and
as fixtures for the checker, the bench and the runtime's tests.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from collections.abc import Hashable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from xpolicylab.embodiments import ACTION_MODES, Embodiment, get_embodiment
from xpolicylab.model import Model, Observation, PolicyMetadata, as_model


class _ReferencePolicy(Model):
    """Shared configuration: ``embodiment``, ``action_mode`` (joint|ee), ``chunk_size``; ``cameras``, ``width`` and
    ``height``: the images the policy asks for (none by default). The reference policies never look at images;
    asking for them makes the evaluator render and send them, which is what a test of that path needs."""

    policy_name = "reference"

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
        self._obs: dict[Hashable, Observation] = {}

    @property
    def metadata(self) -> PolicyMetadata:
        return PolicyMetadata(name=self.policy_name, action_mode=self.action_mode, chunk_size=self.chunk_size,
                              action_dim=self.embodiment.action_dim(self.action_mode),
                              embodiment=self.embodiment.name, cameras=self.cameras,
                              image_width=self.image_size[0], image_height=self.image_size[1],
                              batch=True)

    def current_pose(self, obs: Observation) -> np.ndarray:
        """The pose an action in ``action_mode`` would hold: joint_pos[14], or per arm ee_pose + gripper[16]."""
        state = obs["state"]
        if self.action_mode == "joint":
            return np.asarray(state["joint_pos"], dtype=np.float32).reshape(-1)
        ee = np.asarray(state["ee_pose"], dtype=np.float32).reshape(2, 7)
        grip = np.asarray(state["gripper"], dtype=np.float32).reshape(2, 1)
        return np.concatenate([ee, grip], axis=1).reshape(-1)

    def reset(self) -> None:
        self._obs.clear()

    def reset_batch(self, env_ids: Sequence[Hashable]) -> None:
        for env_id in env_ids:
            self._obs.pop(env_id, None)

    def update_obs(self, obs: Observation) -> None:
        self._obs[None] = obs

    def get_action(self) -> np.ndarray:
        return self.get_action_batch([None])[0]

    def update_obs_batch(self, obs_list: Sequence[Observation], env_ids: Sequence[Hashable]) -> None:
        self._obs.update(zip(env_ids, obs_list, strict=True))


class ZeroPolicy(_ReferencePolicy):
    """Holds the current pose: every row of the chunk repeats the observed state."""

    policy_name = "zero"

    def get_action_batch(self, env_ids: Sequence[Hashable]) -> np.ndarray:
        poses = np.stack([self.current_pose(self._obs[e]) for e in env_ids])
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

    def get_action_batch(self, env_ids: Sequence[Hashable]) -> np.ndarray:
        poses = np.stack([self.current_pose(self._obs[e]) for e in env_ids])
        b, d, k = poses.shape[0], poses.shape[1], self.chunk_size
        out = np.repeat(poses[:, None, :], k, axis=1)
        if self.action_mode == "joint":
            out += self.rng.uniform(-self.max_delta, self.max_delta, size=(b, k, d)).astype(np.float32)
            lo, hi = self.embodiment.joint_bounds()
            out = np.clip(out, lo, hi)
            grippers = list(self.embodiment.gripper_indices())
        else:
            for arm in range(2):
                base = 8 * arm
                out[:, :, base:base + 3] += self.rng.uniform(-self.max_delta, self.max_delta, (b, k, 3))
            grippers = [7, 15]
        out[:, :, grippers] = self.rng.uniform(0.0, 1.0, size=(b, k, 2))
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
