"""`policy.on_device`: when a run hands the policy's rule to the backend, why it cannot (with `on`), that `auto`
falls back to the host path without a word, and which runs it makes another run (their identity).

The mjx side (the rule in the tick, zero's parity with the host, random's reproducibility) is
tests/backends_mjx/test_rule_in_tick.py; these run on the mujoco backend and without a backend.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import pytest
from omegaconf import OmegaConf

from dojo.backends.registry import BackendOptions, make_backend
from dojo.cli.run_cmd import _rule_changes_results
from dojo.compiler.spec_library import SpecLibrary
from dojo.compiler.suite_compile import compile_suite
from dojo.evaluation.evaluate import evaluate, run_id_for
from dojo.evaluation.progress import Progress
from dojo.evaluation.results_store import ResultsStore
from dojo.evaluation.policy_link import device_rule_for, on_device_setting, open_policy, policy_identity
from xpolicylab.policies import HoldRule, JitterRule

PACK = Path(__file__).resolve().parents[1] / "recording" / "pack"
POLICY_CONFIGS = Path(__file__).resolve().parents[2] / "dojo" / "cli" / "config" / "policy"
EMBODIMENT = "arx_x5_bimanual"


def _link(name: str, **options: Any) -> Any:
    return open_policy({"name": name, "url": None, **options}, EMBODIMENT)


def test_auto_hands_the_rule_to_a_backend_that_runs_rules_and_off_never_does():
    assert device_rule_for(_link("zero"), "mjx", recording=False, on_device="auto") == HoldRule(8)
    rule = device_rule_for(_link("random", seed=5), "mjx", recording=False, on_device="on")
    assert isinstance(rule, JitterRule) and rule.seed == 5 and not rule.matches_host
    assert device_rule_for(_link("zero"), "mjx", recording=False, on_device="off") is None
    assert device_rule_for(_link("zero"), "mujoco", recording=False, on_device="auto") is None


@pytest.mark.parametrize("name, options, backend, recording, why", [
    ("zero", {}, "mujoco", False, "backend mujoco runs no policy rule inside its step"),
    ("zero", {"action_mode": "ee"}, "mjx", False, r"policy zero \(ee actions\) has no rule a backend can run"),
    ("random", {"cameras": ["head"]}, "mjx", False, r"policy random asks for images \(head\)"),
    ("zero", {}, "mjx", True, "the run records its episodes"),
])
def test_on_says_why_the_policy_cannot_run_in_the_backend(name, options, backend, recording, why):
    link = _link(name, **options)
    with pytest.raises(ValueError, match=f"policy.on_device=on, but {why}"):
        device_rule_for(link, backend, recording=recording, on_device="on")
    assert device_rule_for(link, backend, recording=recording, on_device="auto") is None


def test_the_setting_reads_yaml_booleans_and_refuses_other_words():
    assert [on_device_setting(v) for v in ("auto", "on", True, "off", False)] == ["auto", "on", "on", "off", "off"]
    with pytest.raises(ValueError, match="policy.on_device must be one of auto, on, off, got 'gpu'"):
        on_device_setting("gpu")


def test_every_policy_config_has_the_option_and_no_run_id_carries_it():
    for path in sorted(POLICY_CONFIGS.glob("*.yaml")):
        cfg = OmegaConf.to_container(OmegaConf.load(path))
        assert cfg["on_device"] == "auto", path.name
        assert "on_device" not in policy_identity(cfg) and policy_identity(cfg).items() <= cfg.items()


def test_a_remote_runs_identity_holds_neither_its_token_nor_how_images_travel():
    """The identity is stored in the results store as JSON: a token there is a leaked secret. And a run started
    with shared memory resumes without it (the same images), as one started with an old token resumes with a new
    one."""
    remote = OmegaConf.to_container(OmegaConf.load(POLICY_CONFIGS / "remote.yaml"))
    one = {**remote, "url": "ws://gpu-box:8000", "token": "s3cret-token", "shared_memory": "on"}
    other = {**one, "token": "rotated", "shared_memory": "off"}
    assert "s3cret-token" not in json.dumps(policy_identity(one))
    assert run_id_for({"policy_config": policy_identity(one)}) == run_id_for({"policy_config": policy_identity(other)})
    moved = {**one, "url": "ws://other-box:8000"}  # another server may serve another checkpoint: another run
    assert run_id_for({"policy_config": policy_identity(one)}) != run_id_for({"policy_config": policy_identity(moved)})


def test_only_a_rule_that_gives_other_numbers_in_the_backend_makes_another_run():
    mjx, mujoco = [({"name": "mjx"}, [])], [({"name": "mujoco"}, [])]
    zero, random = _link("zero"), _link("random")
    assert not _rule_changes_results(zero, mjx, False, "auto")  # zero: the host's numbers, bit for bit
    assert _rule_changes_results(random, mjx, False, "auto")  # random: JAX's draws, not numpy's
    assert not _rule_changes_results(random, mjx, False, "off")
    assert not _rule_changes_results(random, mjx, True, "auto")  # recorded: on the host
    assert not _rule_changes_results(random, mujoco, False, "auto")  # run ids of host runs stay as they were
    assert _rule_changes_results(random, mjx + mujoco, False, "auto")  # some episodes detoured to the host
    with pytest.raises(ValueError, match="backend mujoco runs no policy rule"):
        _rule_changes_results(random, mjx + mujoco, False, "on")  # before anything runs


def test_auto_falls_back_to_the_host_path_on_the_mujoco_backend_silently_and_on_refuses(tmp_path, caplog):
    library = SpecLibrary.load([PACK], strict=False)
    queue = list(compile_suite(library, library.get("suite", "short_suite"), tmp_path / "plans").episodes)
    link = _link("zero", chunk_size=4)
    asked = []
    act = link.act
    link.act = lambda obs, ids: asked.append(len(ids)) or act(obs, ids)
    factory = lambda: make_backend("mujoco", BackendOptions(settings={"threads": 1}, action_modes=("joint",)))
    quiet = Progress(len(queue), mode="quiet")
    with ResultsStore(":memory:") as store, caplog.at_level(logging.INFO):
        assert evaluate(queue, factory, link, store, "run", num_envs=2, progress=quiet, on_device="auto") == 2
        assert sum(asked) == 2 * 2 and [r.steps for r in store.rows("run")] == [6, 6]  # two chunks of 4 each
    assert "device" not in caplog.text and not [r for r in caplog.records if r.levelno >= logging.WARNING]
    with pytest.raises(ValueError, match="policy.on_device=on, but backend mujoco runs no policy rule"):
        evaluate(queue, factory, link, ResultsStore(":memory:"), "run", num_envs=2, progress=quiet, on_device="on")
