"""The real backend on the emulated PiPER: a plan's episode with the zero policy, through piper-sdk.

The plan is this folder's one-block PiPER task (tests/real/pack). Checked: observations in the standard
envelope (state, images, meta), the arms held where they are by the zero policy, the horizon ending the
episode with no success claimed (raters score real trials), a reset putting the scene back, and a non-finite
action refused by the safety layer and ending the episode.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("can")
pytest.importorskip("piper_sdk")

from dojo.backends.base import END_HORIZON, END_NONFINITE, EpisodeDone  # noqa: E402
from dojo.backends.real import make  # noqa: E402
from dojo.backends.real.backend import RealBackend  # noqa: E402
from dojo.compiler.plan import compile_plan  # noqa: E402
from dojo.compiler.spec_library import SpecLibrary  # noqa: E402
from xpolicylab.policies import ZeroPolicy  # noqa: E402

PACK = Path(__file__).parent / "pack"


@pytest.fixture(scope="module")
def plan():
    library = SpecLibrary.load([PACK], strict=False)
    return compile_plan(library, library.get("task", "piper_block_probe"), "standard", 0)


@pytest.fixture(scope="module")
def backend(plan):
    with RealBackend(cameras=("head", "left_wrist"), width=64, height=48) as real:
        real.load([plan])
        yield real


def test_a_zero_policy_episode_on_the_emulator(backend, plan, figures) -> None:

    policy = ZeroPolicy({"embodiment": plan.embodiment, "chunk_size": 4})
    obs = backend.reset()[0]
    assert obs["instruction"] == plan.instruction
    assert set(obs["images"]) == {"head", "left_wrist"} and obs["images"]["head"].shape == (48, 64, 3)
    assert obs["images"]["head"].dtype == np.uint8 and obs["images"]["head"].any()
    state = obs["state"]
    assert state["joint_pos"].shape == (14,) and state["joint_vel"].shape == (14,)
    assert state["ee_pose"].shape == (2, 7) and state["gripper"].shape == (2,)
    assert all(v.dtype == np.float32 for v in state.values())
    assert obs["meta"] == {"task": plan.task, "episode": plan.seed, "step": 0, "embodiment": "piper_bimanual",
                           "control_hz": plan.control_hz}
    start = state["joint_pos"].copy()
    steps, chunk, started = 0, [], time.monotonic()
    while True:  # as the runtime does: a chunk of 4 actions, one observation (with images) per chunk
        if not chunk:
            policy.update_obs(obs)
            chunk = list(policy.get_action())
        result = backend.step(chunk.pop(0)[None], observe=[] if chunk else [0])
        steps += 1
        obs = result.obs[0]
        if result.done[0]:
            break
    figures.add("real_backend.step_period_ms(25 Hz; 2 emulated cameras 64x48 every 4th step, software GL)",
                round((time.monotonic() - started) / steps * 1000, 2))
    assert steps == plan.horizon and result.end_reason == [END_HORIZON]
    assert not result.success[0] and result.score[0] == 0.0 and result.stage_times == [{"lifted": None}]
    assert ("images" in obs) == (plan.horizon % 4 == 0)  # images only at the end of a chunk
    assert np.abs(obs["state"]["joint_pos"] - start).max() < 0.01  # held
    assert obs["meta"]["step"] == plan.horizon and result.clipped_total[0] == 0
    with pytest.raises(EpisodeDone):
        backend.step(policy.get_action()[:1])


def test_end_effector_actions_go_through_ik(backend, plan) -> None:
    """The ee zero policy (hold the observed ee pose) keeps the arms where they are: IK of the measured pose."""
    policy = ZeroPolicy({"embodiment": plan.embodiment, "chunk_size": 5, "action_mode": "ee"})
    obs = backend.reset()[0]
    policy.update_obs(obs)
    for action in policy.get_action():
        result = backend.step(action[None], mode="ee")
    assert np.abs(result.obs[0]["state"]["joint_pos"] - obs["state"]["joint_pos"]).max() < 0.01
    assert result.clipped_total[0] == 0


def test_a_reset_restores_the_scene_and_a_non_finite_action_ends_the_episode(backend, plan) -> None:
    obs = backend.reset()[0]
    action = obs["state"]["joint_pos"][None].astype(np.float64)
    action[0, 1] = np.nan
    result = backend.step(action)
    assert result.done[0] and result.end_reason == [END_NONFINITE]
    assert result.clipped[0] == 1 and backend.safety.counters["refused_nonfinite"] == 1
    assert backend.reset()[0]["meta"]["step"] == 0 and backend.safety.counters["refused_nonfinite"] == 0


def test_the_registry_constructor_reads_the_backend_config() -> None:
    from dojo.backends.registry import BackendOptions

    options = BackendOptions(cameras=("head",), width=32, height=24,
                             settings={"driver": "piper", "can": "can_a,can_b", "cameras": {"head": "opencv:2"}})
    with make(options) as real:  # the cameras open with the robot, at load
        assert real.sources == {"head": ("opencv", "2")}
    with pytest.raises(ValueError, match="backend.cameras.head"):
        make(dataclasses.replace(options, settings={"cameras": {"head": "webcam"}}))
    with pytest.raises(ValueError, match="privileged"):
        make(BackendOptions(privileged=True))
    with make(dataclasses.replace(options, cameras=())) as real:
        assert isinstance(real, RealBackend) and real.driver_name == "piper" and real.can == ("can_a", "can_b")
    with make(BackendOptions(settings={"emulator": {"encoder_noise": 0.001}})) as real:
        assert real.driver_name == "emulator" and real.emulator_params.encoder_noise == 0.001
