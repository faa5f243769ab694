"""The checker passes good servers in both dialects and fails each kind of bad reply with a clear reason."""

from __future__ import annotations

import numpy as np
import pytest

from xpolicylab.checker import CheckConfig, run_check, validate_chunk
from xpolicylab.embodiments import EMBODIMENTS, get_embodiment
from xpolicylab.policies import ZeroPolicy, load_policy, save_episode

from conftest import serving

SMALL = {"width": 64, "height": 48, "n": 4}


@pytest.mark.parametrize("protocol", ["xpolicylab", "openpi"])
@pytest.mark.parametrize("policy,mode", [("zero", "joint"), ("zero", "ee"), ("random", "joint"), ("random", "ee")])
def test_reference_policies_pass(protocol, policy, mode):
    model = load_policy(policy, {"action_mode": mode, "chunk_size": 5})
    with serving(model, protocol=protocol) as srv:
        report = run_check(CheckConfig(url=srv.url, protocol=protocol, **SMALL))
    assert report.passed, report.format()
    assert "RESULT: PASS" in report.format() and report.latency["count"] == 4


@pytest.mark.parametrize("embodiment", sorted(EMBODIMENTS))
def test_every_embodiment(embodiment):
    with serving(load_policy("zero", {"embodiment": embodiment})) as srv:
        report = run_check(CheckConfig(url=srv.url, embodiment=embodiment, **SMALL))
    assert report.passed, report.format()


def test_replay_policy_passes(tmp_path):
    emb = get_embodiment("piper_bimanual")
    actions = np.repeat(emb.home_joint_pos()[None], 30, axis=0)
    save_episode(tmp_path / "ep.npz", actions, embodiment=emb.name)
    with serving(load_policy("replay", {"episode": str(tmp_path / "ep.npz"), "chunk_size": 8})) as srv:
        report = run_check(CheckConfig(url=srv.url, embodiment=emb.name, **SMALL))
    assert report.passed, report.format()


class Broken(ZeroPolicy):
    """Zero policy with one defect injected into its chunks."""

    def __init__(self, defect):
        super().__init__({"chunk_size": 4})
        self.defect = defect

    def get_action_batch(self, env_ids):
        out = super().get_action_batch(env_ids)
        if self.defect == "nan":
            out[:, 1, 3] = np.nan
        elif self.defect == "limits":
            out[:, 0, 1] = 9.0
        elif self.defect == "short":
            out = out[:, :2]
        elif self.defect == "width":
            out = out[:, :, :7]
        return out


@pytest.mark.parametrize("defect,words", [("nan", "not finite"), ("limits", "outside"), ("short", "chunk_size=4"),
                                          ("width", "[K, 14]")])
def test_bad_replies_fail_with_a_reason(defect, words):
    with serving(Broken(defect)) as srv:
        report = run_check(CheckConfig(url=srv.url, **SMALL))
    assert not report.passed
    text = report.format()
    assert "RESULT: FAIL" in text and words in text, text


def test_unreachable_server_fails_cleanly():
    report = run_check(CheckConfig(url="ws://127.0.0.1:9", timeout_s=0.5, connect_attempts=2, **SMALL))
    assert not report.passed and "connect" in report.format()


def test_validate_chunk_ee_rules():
    emb = get_embodiment("arx_x5_bimanual")
    good = np.tile(np.array([0.3, 0, 0.2, 1, 0, 0, 0, 0.5], np.float32), (3, 2))
    assert validate_chunk(good, emb, "ee", 3) == []
    bad = good.copy()
    bad[0, 3] = 2.0
    bad[1, 7] = 1.5
    bad[2, 0] = 5.0
    problems = " ".join(validate_chunk(bad, emb, "ee", 3))
    assert "quaternion" in problems and "gripper" in problems and "beyond" in problems


def test_xpolicylab_style_example_is_served_unchanged():
    from pathlib import Path

    example = Path(__file__).resolve().parents[2] / "examples" / "policies" / "xpolicylab_style" / "model.py"
    model = load_policy(str(example), {"chunk_size": 6})
    assert model.metadata.name == "xpolicylab_style" and model.metadata.chunk_size == 6
    with serving(model) as srv:
        report = run_check(CheckConfig(url=srv.url, **SMALL))
    assert report.passed, report.format()
