"""The runtime's one way to ask a policy for actions, whether it runs in this process or behind a server.

`dojo run policy=zero` needs no server: the reference policies are XPolicyLab `Model`s and are called directly,
batched. `policy.url=ws://...` talks to any XPolicyLab or openpi server through the XPolicyLab client, which
brings retries, receive deadlines, reconnects and, for a server on this host, images through shared memory
(`policy.shared_memory`). Both give the loop the same calls.

A policy whose rule is array arithmetic on the robot's joint state (the built-in `zero` and `random`, in joint mode)
also offers it as a `ChunkRule` (`device_rule`), which a backend that steps on a device can run inside its own step
(`Backend.attach_rule`): `policy.on_device` (`device_rule_for`) decides whether a run does.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np

from dojo.backends.base import ChunkRule, HostBuffers
from dojo.backends.registry import runs_policy_rules
from dojo.evaluation.run_dir import LINK_SETTINGS
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

    def device_rule(self) -> ChunkRule | None:
        """The policy's rule as array code a backend may run in its own step (None: ask `act`)."""

    def image_buffers(self) -> HostBuffers | None:
        """Host memory that observations' images reach the policy from without a copy (None: none)."""


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

    def device_rule(self) -> ChunkRule | None:
        """The model's `device_rule()` where it has one (xpolicylab's `zero` and `random`)."""
        offer = getattr(self.model, "device_rule", None)
        return offer() if offer is not None else None

    def image_buffers(self) -> None:
        """A model in this process reads the backend's arrays as they are."""
        return None


class RemotePolicy:
    """A policy server, through the XPolicyLab client (either dialect)."""

    def __init__(self, url: str, protocol: str = "xpolicylab", token: str | None = None, **client_args: Any):
        from xpolicylab.client import PolicyClient

        self.client = PolicyClient(url, protocol, token=token, **client_args)
        self.metadata = self.client.connect()
        # Whether images skip the socket decides a camera run's speed on one host: say which way they go.
        log.info("policy link: %s (%s), arrays %s%s", url, protocol, "through shared memory"
                 if self.client.uses_shared_memory else "through the socket",
                 ", batches as columns" if self.client.sends_columns else "")

    def reset(self, env_ids: Sequence[int]) -> None:
        self.client.reset(env_ids=list(env_ids))

    def act(self, obs: Sequence[Observation], env_ids: Sequence[int]) -> np.ndarray:
        return np.asarray(self.client.infer_batch(list(obs), list(env_ids)), dtype=np.float32)

    def close(self) -> None:
        self.client.close()

    def device_rule(self) -> None:
        """A served policy runs where it is served."""
        return None

    def image_buffers(self) -> HostBuffers | None:
        """Buffers in the client's shared memory when this connection uses it: images there go to the server as a
        reference to where they are (`xpolicylab.shm`, lent buffers)."""
        return _SharedBuffers(self.client) if self.client.uses_shared_memory else None


class _SharedBuffers:
    """`HostBuffers` over a policy client's lent shared memory."""

    def __init__(self, client: Any) -> None:
        self.client = client

    def lend(self, nbytes: int) -> np.ndarray:
        from xpolicylab.shm import NoSharedMemory

        try:
            buffer = self.client.lend_shared(nbytes)
        except NoSharedMemory as exc:
            raise MemoryError(str(exc)) from exc
        if buffer is None:
            raise MemoryError("the policy link no longer uses shared memory")
        return buffer

    def give_back(self, buffer: np.ndarray) -> None:
        self.client.give_back_shared(buffer)


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


ON_DEVICE = ("auto", "on", "off")
"""`policy.on_device`: run the policy's rule inside the backend's step where possible (auto), or else fail (on), or
never (off)."""


def on_device_setting(value: Any) -> str:
    """`policy.on_device` as one of ON_DEVICE (a YAML file reads `on` and `off` as booleans)."""
    text = ("on" if value else "off") if isinstance(value, bool) else str(value)
    if text not in ON_DEVICE:
        raise ValueError(f"policy.on_device must be one of {', '.join(ON_DEVICE)}, got {value!r}")
    return text


def device_rule_for(policy: PolicyLink, backend: str, *, recording: bool, on_device: Any) -> ChunkRule | None:
    """The rule backend `backend` (its registry name) runs inside its step for `policy` in a run (None: the
    policy is asked for every chunk on the host), as `on_device` says (`ON_DEVICE`); with `on`, a ValueError
    saying why it cannot. The run's log, its identity and its loop ask this same question."""
    setting = on_device_setting(on_device)
    if setting == "off":
        return None
    rule = policy.device_rule()
    why = _why_on_the_host(policy.metadata, rule, backend, recording)
    if why is None:
        return rule
    if setting == "on":
        raise ValueError(f"policy.on_device=on, but {why}; policy.on_device=auto runs it on the host then")
    return None


def _why_on_the_host(meta: PolicyMetadata, rule: ChunkRule | None, backend: str, recording: bool) -> str | None:
    """Why the policy must run on the host in this run (None: its rule can run in the backend's step)."""
    if rule is None:
        return (f"policy {meta.name} ({meta.action_mode} actions) has no rule a backend can run: only the built-in "
                "zero and random policies do, with joint actions")
    if meta.cameras:
        return f"policy {meta.name} asks for images ({', '.join(meta.cameras)}), which only the host path sends"
    if recording:
        return "the run records its episodes, which needs every observation and action on the host"
    if not runs_policy_rules(backend):
        return f"backend {backend} runs no policy rule inside its step (it steps on the host)"
    return None


def columnar_setting(value: Any) -> bool:
    """`policy.columnar` as a bool (true/false, or on/off as a command line may write it)."""
    if isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if text not in ("true", "false", "on", "off"):
        raise ValueError(f"policy.columnar must be true or false, got {value!r}")
    return text in ("true", "on")


def policy_identity(cfg: dict[str, Any]) -> dict[str, Any]:
    """A policy config as a run's identity holds it: without its `LINK_SETTINGS`, so that a run resumes whichever
    way it reaches its policy, and no secret is stored."""
    return {k: v for k, v in cfg.items() if k not in LINK_SETTINGS}


def open_policy(cfg: dict[str, Any], embodiment: str) -> PolicyLink:
    """The policy a run's config names: `url` set -> a server; otherwise a built-in or importable Model."""
    if cfg.get("url"):
        return RemotePolicy(str(cfg["url"]), str(cfg.get("protocol", "xpolicylab")), cfg.get("token"),
                            shared_memory=cfg.get("shared_memory", "auto"),
                            columnar=columnar_setting(cfg.get("columnar", True)))
    from xpolicylab.policies import load_policy

    options = {k: v for k, v in cfg.items()
               if k not in ("name", "url", "protocol", "token", *LINK_SETTINGS)}
    name = RUNTIME_POLICIES.get(str(cfg["name"]), str(cfg["name"]))
    return InProcessPolicy(load_policy(name, {"embodiment": embodiment, **options}))
