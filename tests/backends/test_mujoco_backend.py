"""The CPU backend through the Backend interface: observations, stepping, episode ends, clipping, refills, and a
scripted end-effector rollout that solves the test pack's stack task."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from dojo.backends import base
from dojo.backends.mujoco import backend as backend_module
from dojo.backends.mujoco.backend import MujocoBackend
from dojo.backends.rotations import mat_to_quat


@pytest.fixture
def backend():
    with MujocoBackend(num_threads=2) as b:
        yield b


def hold(obs: list[dict]) -> np.ndarray:
    """Joint actions that hold every environment where it is."""
    return np.stack([o["state"]["joint_pos"] for o in obs]).astype(np.float64)


def test_reset_observations_follow_the_contract(backend, stack_plan):
    backend.load([stack_plan, stack_plan])
    obs = backend.reset()
    assert backend.num_envs == 2 and len(obs) == 2
    o = obs[0]
    assert o["instruction"] == stack_plan.instruction and "images" not in o
    state = o["state"]
    assert {k: (v.shape, v.dtype) for k, v in state.items()} == {
        "joint_pos": ((14,), np.float32), "joint_vel": ((14,), np.float32),
        "ee_pose": ((2, 7), np.float32), "gripper": ((2,), np.float32)}
    assert np.allclose(state["joint_pos"][[6, 13]], 1.0) and np.allclose(state["gripper"], 1.0)  # open at home
    assert np.allclose(np.linalg.norm(state["ee_pose"][:, 3:], axis=1), 1.0, atol=1e-6)
    assert o["meta"] == {"task": "stack_test", "episode": 0, "step": 0, "embodiment": "arx_x5_bimanual",
                         "control_hz": 25.0}


def test_step_holds_still_and_counts_steps(backend, stack_plan):
    backend.load([stack_plan])
    obs = backend.reset()
    for _ in range(3):
        result = backend.step(hold(obs))
    assert result.steps.tolist() == [3] and not result.done[0] and result.end_reason == [None]
    assert result.stage_times == [{"lifted": None, "placed": None}] and result.score.tolist() == [0.0]
    assert np.allclose(result.obs[0]["state"]["joint_pos"], obs[0]["state"]["joint_pos"], atol=2e-3)
    assert result.obs[0]["meta"]["step"] == 3


def test_episode_ends_at_the_horizon_and_must_be_reset(backend, stack_plan):
    short = dataclasses.replace(stack_plan, horizon=3)
    backend.load([short])
    obs = backend.reset()
    done = [bool(backend.step(hold(obs)).done[0]) for _ in range(3)]
    assert done == [False, False, True]
    with pytest.raises(base.EpisodeDone):
        backend.step(hold(obs))
    assert backend.reset([0])[0]["meta"]["step"] == 0
    result = backend.step(hold(obs))
    assert result.steps.tolist() == [1] and not result.done[0]


def test_nonfinite_action_ends_only_that_episode(backend, stack_plan):
    backend.load([stack_plan, stack_plan])
    obs = backend.reset()
    actions = hold(obs)
    actions[1, 2] = np.nan
    result = backend.step(actions)
    assert result.done.tolist() == [False, True]
    assert result.end_reason == [None, base.END_NONFINITE] and not result.success[1]
    assert result.steps.tolist() == [1, 0]  # the bad action was never applied
    assert np.array_equal(result.obs[1]["state"]["joint_pos"], obs[1]["state"]["joint_pos"])
    assert backend.step(actions[:1], env_ids=[0]).env_ids.tolist() == [0]


def test_clipped_actions_are_counted_per_step_and_episode(backend, stack_plan):
    backend.load([stack_plan])
    obs = backend.reset()
    actions = hold(obs)
    actions[0, 0], actions[0, 6] = 99.0, -1.0
    assert backend.step(actions).clipped.tolist() == [2]
    result = backend.step(actions)
    assert result.clipped.tolist() == [2] and result.clipped_total.tolist() == [4]
    backend.reset()
    assert backend.step(hold(obs)).clipped_total.tolist() == [0]


def test_wrong_action_shape_is_refused(backend, stack_plan):
    backend.load([stack_plan])
    backend.reset()
    with pytest.raises(ValueError, match=r"shape \(1, 16\)"):
        backend.step(np.zeros((1, 14)), mode="ee")


def test_continuous_refill_and_model_reuse(backend, stack_plan, probe_plan, monkeypatch):
    compiles = []
    real = backend_module.compile_program
    monkeypatch.setattr(backend_module, "compile_program",
                        lambda plan, model: compiles.append(plan.hash) or real(plan, model))
    backend.load([stack_plan, stack_plan])
    obs = backend.reset()
    for _ in range(2):
        backend.step(hold(obs))
    refill = backend.reset([1], plans=[probe_plan])
    assert refill[0]["instruction"] == probe_plan.instruction
    result = backend.step(hold([obs[0], refill[0]]))
    assert result.steps.tolist() == [3, 1]  # slot 0 kept running
    assert result.stage_times[1] == {"first_in": None, "both_in": None, "pressed_twice": None}
    backend.reset([1], plans=[dataclasses.replace(stack_plan)])  # a new Plan object of a known hash
    backend.reset()
    assert compiles == [stack_plan.hash, probe_plan.hash]  # resets never recompile


def test_one_embodiment_per_backend(backend, stack_plan):
    other = dataclasses.replace(stack_plan, hash="other", embodiment="piper_bimanual")
    backend.load([stack_plan, stack_plan])
    with pytest.raises(ValueError, match="one embodiment"):
        backend.reset([0], plans=[other])


def test_ee_mode_holds_the_current_pose(backend, stack_plan):
    backend.load([stack_plan])
    obs = backend.reset()
    ee = obs[0]["state"]["ee_pose"].astype(np.float64)
    action = np.concatenate([ee[0], [1.0], ee[1], [1.0]])[None]
    for _ in range(3):
        result = backend.step(action, mode="ee")
    assert np.allclose(result.obs[0]["state"]["joint_pos"], obs[0]["state"]["joint_pos"], atol=2e-3)
    assert result.clipped.tolist() == [0]


def base_frame(plan, arm: str) -> tuple[np.ndarray, np.ndarray]:
    """Position and rotation of an arm's base in the world (to script world-frame targets)."""
    data = plan.initial_data()
    base_id = plan.model().body(f"{arm}_base").id
    return data.xpos[base_id].copy(), data.xmat[base_id].reshape(3, 3).copy()


def test_scripted_ee_pick_and_place_succeeds(backend, stack_plan, set_free_pose):
    """Grasp the block top-down with the left arm, lift it, put it on the plate (moved within easy reach)."""
    model = stack_plan.model()
    qpos = np.asarray(stack_plan.init_qpos)
    block = stack_plan.initial_data().xpos[model.body("block").id].copy()
    plate = np.array([block[0] + 0.12, block[1] + 0.05, 0.76])
    set_free_pose(stack_plan, qpos, "plate", plate)
    plan = dataclasses.replace(stack_plan, hash="stack_test-plate-moved", init_qpos=qpos.tolist())
    backend.load([plan])
    obs = backend.reset()
    base_pos, base_rot = base_frame(plan, "left")
    down = np.column_stack([base_rot.T @ [0.0, 0.0, -1.0], base_rot.T @ [0.0, 1.0, 0.0]])
    down = np.column_stack([down, np.cross(down[:, 0], down[:, 1])])  # approach (x) down, fingers close along y
    quat = mat_to_quat(np, down[None])[0]
    right = np.concatenate([obs[0]["state"]["ee_pose"][1], [1.0]])
    start = base_pos + base_rot @ obs[0]["state"]["ee_pose"][0, :3]

    def leg(a, b, steps, grip, hold_steps=10):
        return [(a + (b - a) * min(1.0, (k + 1) / steps), grip) for k in range(steps + hold_steps)]

    above_block, above_plate = block + [0, 0, 0.12], plate + [0, 0, 0.14]
    place = plate + [0, 0, 0.01 + 0.02 + 0.005]
    script = (leg(start, above_block, 40, 1.0) + leg(above_block, block, 30, 1.0) + [(block, 0.0)] * 15
              + leg(block, above_block, 30, 0.0) + leg(above_block, above_plate, 30, 0.0)
              + leg(above_plate, place, 25, 0.0) + [(place, 1.0)] * 25)
    for target, grip in script:
        action = np.concatenate([base_rot.T @ (target - base_pos), quat, [grip], right])[None]
        result = backend.step(action, mode="ee")
        if result.done[0]:
            break
    assert result.end_reason == [base.END_SUCCESS] and result.success[0] and result.score[0] == pytest.approx(100.0)
    times = result.stage_times[0]
    assert times["lifted"] is not None and times["placed"] is not None and times["lifted"] < times["placed"]


def test_diverged_physics_ends_the_episode(backend, stack_plan, monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)  # MuJoCo writes its warning to MUJOCO_LOG.TXT in the working directory
    qvel = list(stack_plan.init_qvel)
    qvel[-1] = 1e12  # the plate spinning absurdly fast
    backend.load([dataclasses.replace(stack_plan, hash="stack_test-diverges", init_qvel=qvel)])
    obs = backend.reset()
    result = backend.step(hold(obs))
    assert result.done.tolist() == [True] and result.end_reason == [base.END_UNSTABLE] and not result.success[0]


def test_compiled_plans_cache_is_bounded(backend, stack_plan, monkeypatch):
    compiles = []
    real = backend_module.compile_program
    monkeypatch.setattr(backend_module, "compile_program",
                        lambda plan, model: compiles.append(plan.hash) or real(plan, model))
    monkeypatch.setattr(backend_module, "CACHED_PLANS", 1)
    variants = [dataclasses.replace(stack_plan, hash=f"variant-{k}") for k in range(3)]
    backend.load([variants[0]])
    for plan in (variants[1], variants[2], variants[1], variants[0]):
        backend.reset([0], plans=[plan])
    assert compiles == ["variant-0", "variant-1", "variant-2", "variant-0"]  # 1 kept while 2 runs; 0 dropped


def test_prefetched_plans_are_compiled_once_in_the_background(backend, stack_plan, probe_plan, monkeypatch):
    compiles = []
    real = backend_module.compile_program
    monkeypatch.setattr(backend_module, "compile_program",
                        lambda plan, model: compiles.append(plan.hash) or real(plan, model))
    backend.load([stack_plan])
    backend.reset()
    backend.prefetch([probe_plan, probe_plan, stack_plan])
    obs = backend.reset([0], plans=[probe_plan])
    assert obs[0]["instruction"] == probe_plan.instruction
    assert compiles == [stack_plan.hash, probe_plan.hash]


def test_delta_modes_move_relative_to_the_measured_state(backend, stack_plan):
    backend.load([stack_plan, stack_plan])
    obs = backend.reset()
    start = obs[0]["state"]["joint_pos"].copy()
    delta = np.zeros((1, 14))
    delta[0, 0], delta[0, 6], delta[0, 13] = 0.05, 1.0, 1.0  # turn the left base joint, grippers stay open
    for _ in range(5):
        result = backend.step(delta, env_ids=[0], mode="delta_joint")
    moved = result.obs[0]["state"]["joint_pos"] - start
    assert 0.1 < moved[0] < 0.25 and np.abs(moved[1:6]).max() < 0.02  # servo lag: under 5 x 0.05
    still = np.array([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0] * 2])
    ee = obs[1]["state"]["ee_pose"].copy()
    for _ in range(3):
        result = backend.step(still, env_ids=[1], mode="delta_ee")
    assert np.abs(result.obs[0]["state"]["ee_pose"] - ee).max() < 2e-3 and result.clipped.tolist() == [0]
