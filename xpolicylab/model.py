"""The ``Model`` interface every policy implements once to be evaluated anywhere.

A simple policy writes three methods (``reset``, ``update_obs``, ``get_action``); the batched methods default
to looping over them, so the server can always answer a batched ``infer``. A policy that can run one forward
pass for many environments overrides ``update_obs_batch``/``get_action_batch`` and the server advertises it; one
that wants the batch's images already stacked (``[B, H, W, 3]`` per camera, as a columnar request carries them)
overrides ``update_obs_columns`` too.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from xpolicylab.columns import split as columns_split
from xpolicylab.embodiments import CAMERAS

Observation = dict[str, Any]


@dataclass
class PolicyMetadata:
    """What a policy tells the evaluator on connect (sent in ``hello_ack`` and as openpi's metadata)."""

    name: str
    action_mode: str = "joint"
    chunk_size: int = 1
    action_dim: int = 14
    embodiment: str | None = None
    cameras: tuple[str, ...] = CAMERAS  # cameras the policy reads; () when it reads none
    image_width: int | None = 640  # None: any resolution
    image_height: int | None = 480
    batch: bool = False  # True when get_action_batch is a real batched forward pass
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["cameras"] = list(self.cameras)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PolicyMetadata:
        """Read metadata sent by any server; fields it does not know go to ``extra``."""
        known = {f for f in cls.__dataclass_fields__ if f != "extra"}
        kwargs = {k: v for k, v in data.items() if k in known}
        if "cameras" in kwargs:
            kwargs["cameras"] = tuple(kwargs["cameras"])
        extra = dict(data.get("extra") or {})
        extra.update({k: v for k, v in data.items() if k not in known and k != "extra"})
        return cls(**{"name": str(data.get("name", "unknown")), **kwargs}, extra=extra)


class Model:
    """Base class of policies. Subclasses implement ``update_obs``, ``get_action`` and ``metadata``.

    ``get_action`` returns an action chunk, ``float32[K, D]`` in ``metadata.action_mode``.
    The server never calls a model from two threads at once.
    """

    borrows_observations: bool = False
    """True when the model keeps no array of the observations it is given once it has answered (it copies what it
    keeps, or reads only small fields): a server on the client's host then hands it read-only views of the client's
    shared memory instead of copies, which at 2,048 environments with three cameras saves copying about 1 GB per
    request. The client writes the next request's images into the same memory once it has the reply."""

    def __init__(self, config: dict[str, Any] | None = None) -> None:
        self.config: dict[str, Any] = dict(config or {})

    @property
    def metadata(self) -> PolicyMetadata:
        raise NotImplementedError(f"{type(self).__name__} must define a `metadata` property returning PolicyMetadata")

    def reset(self) -> None:
        """Forget the current episode. The default has nothing to forget."""

    def update_obs(self, obs: Observation) -> None:
        raise NotImplementedError(f"{type(self).__name__} must implement update_obs(obs)")

    def get_action(self) -> np.ndarray:
        raise NotImplementedError(f"{type(self).__name__} must implement get_action()")

    def reset_batch(self, env_ids: Sequence[Hashable]) -> None:
        """Forget the episodes of ``env_ids``; a model without per-environment state just resets."""
        self.reset()

    def update_obs_batch(self, obs_list: Sequence[Observation], env_ids: Sequence[Hashable]) -> None:
        """Receive one observation per environment; the default keeps them for ``get_action_batch``."""
        # setdefault: subclasses that skip super().__init__() still get the batched defaults
        self.__dict__.setdefault("_pending", {}).update(zip(env_ids, obs_list, strict=True))

    def update_obs_columns(self, columns: dict[str, Any], env_ids: Sequence[Hashable]) -> None:
        """Receive a columnar batch (``xpolicylab.columns``: each array with the batch as its first axis, each other
        value a list with one entry per environment). The default hands ``update_obs_batch`` the observations
        it holds, environment by environment (their arrays are views of the columns)."""
        self.update_obs_batch(columns_split(columns, len(env_ids)), env_ids)

    def get_action_batch(self, env_ids: Sequence[Hashable]) -> np.ndarray:
        """Return ``float32[B, K, D]``; the default runs ``update_obs``/``get_action`` per environment."""
        pending = self.__dict__.setdefault("_pending", {})
        chunks = []
        for env_id in env_ids:
            self.update_obs(pending.pop(env_id))
            chunks.append(np.asarray(self.get_action(), dtype=np.float32))
        return np.stack(chunks)

    def prepare_case(self, meta: dict[str, Any]) -> Any:
        """Hook called before the trials of one evaluation case (task, setting); optional."""
        return None

    def on_trial_end(self, result: dict[str, Any]) -> Any:
        """Hook called with a trial's outcome; optional."""
        return None



class _Adapted(Model):
    """Serves a policy written against XPolicyLab's duck-typed interface (``update_obs``/``get_action``,
    optional ``reset``, hooks and ``metadata``) without changing it."""

    def __init__(self, policy: Any) -> None:
        super().__init__(getattr(policy, "config", None) if isinstance(getattr(policy, "config", None), dict) else None)
        self.policy = policy

    @property
    def metadata(self) -> PolicyMetadata:
        meta = getattr(self.policy, "metadata", None)
        if isinstance(meta, PolicyMetadata):
            return meta
        if isinstance(meta, dict):
            return PolicyMetadata.from_dict({"name": type(self.policy).__name__, **meta})
        return PolicyMetadata(name=type(self.policy).__name__)

    def reset(self) -> None:
        if callable(getattr(self.policy, "reset", None)):
            self.policy.reset()

    def update_obs(self, obs: Observation) -> None:
        self.policy.update_obs(obs)

    def get_action(self) -> Any:
        return self.policy.get_action()

    def prepare_case(self, meta: dict[str, Any]) -> Any:
        hook = getattr(self.policy, "prepare_case", None)
        return hook(meta) if callable(hook) else None

    def on_trial_end(self, result: dict[str, Any]) -> Any:
        hook = getattr(self.policy, "on_trial_end", None)
        return hook(result) if callable(hook) else None


def as_model(policy: Any) -> Model:
    """``policy`` itself if it is a Model, else an adapter for XPolicyLab-style duck-typed policies."""
    if isinstance(policy, Model):
        return policy
    if not (callable(getattr(policy, "update_obs", None)) and callable(getattr(policy, "get_action", None))):
        raise TypeError(f"{type(policy).__name__} has no update_obs()/get_action(); it cannot be served")
    return _Adapted(policy)
