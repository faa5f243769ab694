"""The oracle is privileged and says so, reads only the privileged observation, and `dojo run` can open it."""

from __future__ import annotations

import numpy as np
import pytest
from dojo.backends.mujoco.backend import MujocoBackend
from dojo.compiler.plan import Plan
from dojo.experts.validity import plan_files
from dojo.experts.oracle import OraclePolicy
from dojo.evaluation.policy_link import open_policy


@pytest.fixture(scope="module")
def stack_plan(library, plan_cache) -> tuple[Plan, str]:
    path = plan_files(library, ["stack_blocks"], 1, plan_cache)["stack_blocks"][0]
    return Plan.load(path), str(path)


def test_metadata_marks_the_oracle_privileged():
    meta = OraclePolicy().metadata
    assert meta.name == "oracle" and meta.extra["privileged"] is True
    assert meta.action_mode == "joint" and meta.action_dim == 14 and meta.cameras == ()
    assert "PRIVILEGED" in OraclePolicy.__doc__


def test_dojo_run_opens_the_oracle_by_name():
    link = open_policy({"name": "oracle", "url": None, "protocol": "xpolicylab", "chunk_size": 2},
                       "arx_x5_bimanual")
    assert isinstance(link.model, OraclePolicy) and link.metadata.chunk_size == 2


def test_privileged_observation_only_when_asked(stack_plan):
    plan, path = stack_plan
    with MujocoBackend(num_threads=1) as plain:
        plain.load([plan])
        assert "privileged" not in plain.reset()[0]
    with MujocoBackend(num_threads=1, privileged=True, plan_paths={plan.hash: path}) as backend:
        backend.load([plan])
        priv = backend.reset()[0]["privileged"]
    model = plan.model()
    assert priv["qpos"].shape == (model.nq,) and priv["qvel"].shape == (model.nv,)
    assert priv["qpos"].dtype == np.float64 and np.allclose(priv["qpos"], plan.init_qpos)
    assert priv["plan_hash"] == plan.hash and priv["plan_path"] == path


def test_oracle_refuses_unprivileged_observations(stack_plan):
    plan, _ = stack_plan
    with MujocoBackend(num_threads=1) as backend:
        backend.load([plan])
        obs = backend.reset()
    oracle = OraclePolicy()
    oracle.update_obs_batch(obs, [0])
    with pytest.raises(ValueError, match="privileged"):
        oracle.get_action_batch([0])


def test_oracle_chunks_are_joint_targets_within_limits(stack_plan):
    plan, path = stack_plan
    with MujocoBackend(num_threads=1, privileged=True, plan_paths={plan.hash: path}) as backend:
        backend.load([plan])
        obs = backend.reset()
        oracle = OraclePolicy({"chunk_size": 5})
        oracle.reset_batch([0])
        for _ in range(20):
            oracle.update_obs_batch(obs, [0])
            chunk = oracle.get_action_batch([0])
            assert chunk.shape == (1, 5, 14) and chunk.dtype == np.float32
            for row in chunk[0]:
                result = backend.step(row[None], [0])
            obs = result.obs
        assert result.clipped_total[0] == 0  # the expert never asks for more than the joints allow
