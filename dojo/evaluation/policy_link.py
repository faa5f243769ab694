"""The runtime's one way to ask a policy for actions, whether it runs in this process or behind a server.

`dojo run policy=zero` needs no server: the reference policies are XPolicyLab `Model`s and are called directly,
batched. `policy.url=ws://...` talks to any XPolicyLab or openpi server through the XPolicyLab client, which
brings retries, receive deadlines, reconnects and, for a server on this host, images through shared memory
(`policy.shared_memory`). Both give the loop the same three calls.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np

from xpolicylab.model import Model, Observation, PolicyMetadata

log = logging.getLogger(__name__)


class PolicyLink(Protocol):
    """What the evaluation loop needs from a policy."""

    metadata: PolicyMetadata

    def reset(self, env_ids: Sequence[int]) -> None:
        """New episodes start in these environments."""

    def act(self, obs: Sequence[Observation], env_ids: Sequence[int]) -> np.ndarray:
        """One action chunk per environment, float32[B, K, D]."""

    def close(self) -> None:
        """Release the connection or the model."""


class InProcessPolicy:
    """A `Model` called directly (its batched methods: one call for every environment that needs actions)."""

    def __init__(self, model: Model):
        self.model = model
        self.metadata = model.metadata

    def reset(self, env_ids: Sequence[int]) -> None:
        self.model.reset_batch(list(env_ids))

    def act(self, obs: Sequence[Observation], env_ids: Sequence[int]) -> np.ndarray:
        self.model.update_obs_batch(list(obs), list(env_ids))
        return np.asarray(self.model.get_action_batch(list(env_ids)), dtype=np.float32)

    def close(self) -> None:
        pass


class RemotePolicy:
    """A policy server, through the XPolicyLab client (either dialect)."""

    def __init__(self, url: str, protocol: str = "xpolicylab", token: str | None = None, **client_args: Any):
        from xpolicylab.client import PolicyClient

        self.client = PolicyClient(url, protocol, token=token, **client_args)
        self.metadata = self.client.connect()
        # Whether images skip the socket decides a camera run's speed on one host: say which way they go.
        log.info("policy link: %s (%s), arrays %s", url, protocol, "through shared memory"
                 if self.client.uses_shared_memory else "through the socket")

    def reset(self, env_ids: Sequence[int]) -> None:
        self.client.reset(env_ids=list(env_ids))

    def act(self, obs: Sequence[Observation], env_ids: Sequence[int]) -> np.ndarray:
        return np.asarray(self.client.infer_batch(list(obs), list(env_ids)), dtype=np.float32)

    def close(self) -> None:
        self.client.close()


PRIVILEGED_NOTE = "privileged reference: reads the simulator state, not a leaderboard entry"
"""How a run's table and a report mark a policy whose metadata says `extra.privileged` (the scripted `oracle`):
its 100% shows that the tasks are solvable, not what a policy that sees only cameras and joints can do."""


def is_privileged(metadata: PolicyMetadata | dict[str, Any]) -> bool:
    """Does a policy (its metadata, or the metadata dict a result row stores) read the simulator state?"""
    extra = metadata.extra if isinstance(metadata, PolicyMetadata) else (metadata.get("extra") or {})
    return bool(extra.get("privileged"))


RUNTIME_POLICIES = {"oracle": "dojo.experts.oracle:OraclePolicy"}
"""Reference policies that need the simulator (so they live here, not in the MuJoCo-free xpolicylab)."""


def policy_config_for(cfg: dict[str, Any], worker: int) -> dict[str, Any]:
    """The policy config of one worker of a run: `url` may list servers, one per worker (worker i talks to the
    i-th, round robin when there are more workers), so that a policy too slow for every worker at once can be
    served several times. A single `url` is every worker's."""
    urls = cfg.get("url")
    if isinstance(urls, (list, tuple)):
        if not urls:
            raise ValueError("policy.url is an empty list: give one server, or one per worker")
        return {**cfg, "url": urls[worker % len(urls)]}
    return cfg


def open_policy(cfg: dict[str, Any], embodiment: str) -> PolicyLink:
    """The policy a run's config names: `url` set -> a server; otherwise a built-in or importable Model."""
    if cfg.get("url"):
        return RemotePolicy(str(cfg["url"]), str(cfg.get("protocol", "xpolicylab")), cfg.get("token"),
                            shared_memory=cfg.get("shared_memory", "auto"))
    from xpolicylab.policies import load_policy

    options = {k: v for k, v in cfg.items() if k not in ("name", "url", "protocol", "token", "shared_memory")}
    name = RUNTIME_POLICIES.get(str(cfg["name"]), str(cfg["name"]))
    return InProcessPolicy(load_policy(name, {"embodiment": embodiment, **options}))
