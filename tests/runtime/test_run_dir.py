"""Run folders: `<root>/<suite>/<policy>/<key>`, the key short, stable and safe to type in a shell."""

from __future__ import annotations

import re

import pytest

from dojo.evaluation.run_dir import DEFAULT_KEY, results_root, run_key

SAFE = re.compile(r"^[A-Za-z0-9._=-]+$")


def test_no_override_that_changes_results_is_the_default_key() -> None:
    assert run_key([]) == DEFAULT_KEY
    # The suite and policy are the folders above the key; the rest only change how a run executes.
    assert run_key(["policy=zero", "suite=robodojo_sim", "num_envs=16", "progress=quiet", "jobs=2",
                    "results=r.sqlite", "report=outputs/report/r.json", "plans=p", "episode_timeout_s=9"]) == "default"


def test_the_key_is_sorted_and_filesystem_safe() -> None:
    key = run_key(["seeds=[0,1,2]", "episodes=4", "backend=mjx"])
    assert key == "backend=mjx_episodes=4_seeds=0-1-2"
    assert run_key(["episodes=4", "backend=mjx", "seeds=[0,1,2]"]) == key  # the same run, whatever the order
    assert run_key(["episodes=3", "backend=mjx", "seeds=[0,1,2]", "episodes=4"]) == key  # the last value counts
    for overrides in (["tasks=[stack_blocks,push_t]"], ["packs=[/a/b c/d:e]"], ["+x='a,b'"], ["~width"],
                      ["policy.protocol=openpi"]):
        assert SAFE.match(run_key(overrides)), overrides


def test_a_server_address_and_token_stay_out_of_the_path() -> None:
    """`policy.url=ws://host:port` used to split the folder in two (`ws:/host:port`); a token is a secret."""
    assert run_key(["policy=remote", "policy.url=ws://127.0.0.1:19000", "policy.token=s3cret",
                    "policy.shared_memory=off", "episodes=1"]) == "episodes=1"


def test_where_a_built_in_policy_runs_stays_out_of_the_path() -> None:
    """`policy.on_device=off` gives `zero` the same results: the same folder (a `random` run on the device has its
    own run id inside the store)."""
    assert run_key(["policy=zero", "policy.on_device=off", "episodes=1"]) == run_key(["policy=zero", "episodes=1"])


def test_long_values_keep_a_readable_head_and_a_hash() -> None:
    long_a = run_key(["packs=[/home/someone/projects/very/long/path/to/pack_a]"])
    long_b = run_key(["packs=[/home/someone/projects/very/long/path/to/pack_b]"])
    assert long_a != long_b and long_a.startswith("packs=home-someone") and len(long_a) <= 40
    assert len(run_key([f"k{i}=value-number-{i}" for i in range(30)])) <= 96


@pytest.mark.parametrize("env, expected", [(None, "outputs"), ("/data/dojo", "/data/dojo")])
def test_results_root(monkeypatch: pytest.MonkeyPatch, env: str | None, expected: str) -> None:
    if env is None:
        monkeypatch.delenv("DOJO_OUTPUTS", raising=False)
    else:
        monkeypatch.setenv("DOJO_OUTPUTS", env)
    assert str(results_root()) == expected
