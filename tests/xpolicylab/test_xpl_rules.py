"""The reference policies' rules as array code (`device_rule`): what a simulator runs in place of the policy, with
numpy here (tests/backends_mjx/test_rule_in_tick.py runs them under JAX, in the mjx backend's tick)."""

from __future__ import annotations

import numpy as np

from xpolicylab.embodiments import get_embodiment
from xpolicylab.policies import HoldRule, JitterRule, load_policy

LO, HI = get_embodiment("arx_x5_bimanual").joint_bounds()
GRIPPERS = [6, 13]


def _observations(n: int, seed: int = 0) -> list[dict]:
    rng = np.random.default_rng(seed)  # poses up to 0.3 rad outside the bounds: clipping shows
    return [{"state": {"joint_pos": rng.uniform(LO - 0.3, HI + 0.3).astype(np.float32)}} for _ in range(n)]


def test_rules_are_offered_in_joint_mode_only():
    assert load_policy("zero", {"chunk_size": 5}).device_rule() == HoldRule(5)
    rule = load_policy("random", {"chunk_size": 5, "seed": 7, "max_delta": 0.1}).device_rule()
    assert rule == JitterRule(5, 7, 0.1, tuple(map(float, LO)), tuple(map(float, HI))) and rule.draws == 16
    assert HoldRule.matches_host and not JitterRule.matches_host and HoldRule.draws == 0
    for name in ("zero", "random"):
        assert load_policy(name, {"action_mode": "ee"}).device_rule() is None


def test_hold_rows_are_the_pose_the_chunk_started_from():
    pose = np.arange(28, dtype=np.float32).reshape(2, 14)
    np.testing.assert_array_equal(HoldRule(3).row(np, pose, np.zeros((2, 0), np.float32)), pose)


def test_jitter_rows_stay_within_the_bounds_and_max_delta_and_grippers_are_the_draws():
    rule = load_policy("random", {"max_delta": 0.2}).device_rule()
    rng = np.random.default_rng(1)
    pose = np.stack([o["state"]["joint_pos"] for o in _observations(512)])
    uniform = rng.random((512, rule.draws)).astype(np.float32)
    rows = rule.row(np, pose, uniform)
    assert rows.dtype == np.float32 and rows.shape == pose.shape
    assert np.all((rows >= LO) & (rows <= HI))
    np.testing.assert_array_equal(rows[:, GRIPPERS], uniform[:, -2:])
    arms = [j for j in range(14) if j not in GRIPPERS]
    inside = (pose[:, arms] >= LO[arms]) & (pose[:, arms] <= HI[arms])
    moved = np.abs(rows[:, arms] - pose[:, arms])
    assert np.all(moved[inside] <= 0.2 + 1e-6) and moved[inside].max() > 0.15  # the whole range is used


def test_random_on_the_host_draws_numpys_stream_as_it_always_did():
    """The host policy's chunk is the rule on its own draws, and those are the numbers it gave before the rule
    existed: numpy's uniform(-max_delta, max_delta) for every value, then uniform(0, 1) for the grippers."""
    policy = load_policy("random", {"seed": 11, "chunk_size": 4})
    obs = _observations(3, seed=2)
    policy.update_obs_batch(obs, [0, 1, 2])
    chunk = policy.get_action_batch([0, 1, 2])
    rng = np.random.default_rng(11)
    pose = np.stack([o["state"]["joint_pos"] for o in obs])
    expected = np.repeat(pose[:, None, :], 4, axis=1) + rng.uniform(-0.05, 0.05, (3, 4, 14)).astype(np.float32)
    expected = np.clip(expected, LO, HI)
    expected[:, :, GRIPPERS] = rng.uniform(0.0, 1.0, (3, 4, 2))
    np.testing.assert_array_equal(chunk, expected)
    assert len({tuple(row) for row in chunk[0]}) == 4  # a fresh draw per row
