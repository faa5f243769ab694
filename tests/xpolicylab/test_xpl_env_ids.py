"""Environment ids kept apart between the clients of one server (`xpolicylab.env_ids`): two evaluators that number
their environments alike never share a model's per-environment state."""

from __future__ import annotations

import time

import numpy as np

from xpolicylab.client import PolicyClient
from xpolicylab.env_ids import EnvIdSpace
from xpolicylab.policies import ZeroPolicy

from conftest import serving, small_obs


def test_ids_pass_unchanged_until_another_connection_holds_them():
    space = EnvIdSpace()
    first, second = space.connection(), space.connection()
    assert first.to_model([0, 1, "arm"]) == [0, 1, "arm"]
    assert second.to_model([1, 0, "arm", 7]) == [2, 3, "arm#1", 7]  # smallest free integers; a suffixed string
    assert second.to_model([0, 1]) == [3, 2]  # fixed for the connection's life
    assert first.to_model([2]) == [4]  # the first connection's new id, now held by the second
    assert sorted(map(str, first.release())) == ["0", "1", "4", "arm"]
    third = space.connection()
    assert third.to_model([0, "arm"]) == [0, "arm"]  # released ids are free again


class Keeper(ZeroPolicy):
    """Records the ids the model is given, per call, and what it is told to forget."""

    def __init__(self):
        super().__init__({"chunk_size": 2})
        self.seen: list[list] = []
        self.forgotten: list[list] = []

    def reset_batch(self, env_ids):
        self.forgotten.append(list(env_ids))
        super().reset_batch(env_ids)

    def get_action_batch(self, env_ids):
        self.seen.append(list(env_ids))
        return super().get_action_batch(env_ids)


def test_two_clients_with_the_same_ids_reach_different_environments_of_the_model():
    model = Keeper()
    with serving(model) as srv:
        with PolicyClient(srv.url) as a, PolicyClient(srv.url) as b:
            obs_a = [small_obs(seed=1), small_obs(seed=2)]
            obs_b = [small_obs(seed=3), small_obs(seed=4)]
            a.reset(env_ids=[0, 1])
            b.reset(env_ids=[0, 1])
            actions_a = a.infer_batch(obs_a, [0, 1])
            actions_b = b.infer_batch(obs_b, [0, 1])
            actions_a2 = a.infer_batch(obs_a, [0, 1])
        # each client's actions come from its own observations, under its own ids
        for obs, chunk in zip(obs_a + obs_b, list(actions_a) + list(actions_b), strict=True):
            assert np.array_equal(chunk[0], obs["state"]["joint_pos"])
        assert np.array_equal(actions_a, actions_a2)
        assert model.seen == [[0, 1], [2, 3], [0, 1]]
        deadline = time.monotonic() + 5
        while len(model.forgotten) < 4 and time.monotonic() < deadline:  # the closes reach the model
            time.sleep(0.02)
        assert model.forgotten[:2] == [[0, 1], [2, 3]]  # the resets, as the model knows the ids
        assert sorted(map(sorted, model.forgotten[2:])) == [[0, 1], [2, 3]]  # both connections closed: forgotten
        with PolicyClient(srv.url) as c:  # the ids are free again
            c.infer_batch([small_obs(seed=5)], [1])
        assert model.seen[-1] == [1]
