"""A served policy that keeps state per environment id, as a policy with frame history or memory does: from a reset
of an id to the next, every observation under it must be of one episode, each at a later step than the last. Two
evaluators whose episodes reached it under the same id would break that, and it fails the request (the episode
then ends as a policy error)."""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from typing import Any

from xpolicylab.policies import ZeroPolicy


class EpisodeKeeper(ZeroPolicy):
    policy_name = "episode_keeper"

    def __init__(self, config: dict[str, Any] | None = None) -> None:
        super().__init__(config)
        self._held: dict[Hashable, tuple[str, int, int]] = {}

    def reset_batch(self, env_ids: Sequence[Hashable]) -> None:
        super().reset_batch(env_ids)
        for env_id in env_ids:
            self._held.pop(env_id, None)

    def update_obs_batch(self, obs_list: Sequence[Any], env_ids: Sequence[Hashable]) -> None:
        for obs, env_id in zip(obs_list, env_ids, strict=True):
            meta = obs["meta"]
            episode, step = (meta["task"], int(meta["episode"])), int(meta["step"])
            held = self._held.get(env_id)
            if held is not None and (held[:2] != episode or step <= held[2]):
                raise RuntimeError(f"environment {env_id} holds episode {held[:2]} at step {held[2]}, and got "
                                   f"step {step} of episode {episode}")
            self._held[env_id] = (*episode, step)
        super().update_obs_batch(obs_list, env_ids)
