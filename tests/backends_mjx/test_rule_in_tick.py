"""The built-in zero and random policies run inside the mjx backend's tick (`policy.on_device`): zero records what
the host path records, bit for bit; random is reproducible from its seed; a slot refilled starts a fresh chunk. And
the tick with its physics on Warp's lanes (`backend.streams`) records what the jitted tick records.

Real plans (the recording pack's six-step task, two 6-DoF arms) on MuJoCo Warp's CPU device: a backend loads in
about 5 s and steps in about 0.8 s here. The chunk size (4) does not divide the horizon (6), so every episode
starts a second chunk mid-way, and two slots for three episodes refill one of them.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dojo.backends.registry import BackendOptions, make_backend
from dojo.compiler.episodes import PlannedEpisode
from dojo.compiler.spec_library import SpecLibrary
from dojo.compiler.suite_compile import compile_suite
from dojo.evaluation.evaluate import evaluate
from dojo.evaluation.progress import Progress
from dojo.evaluation.results_store import ResultsStore
from dojo.evaluation.policy_link import open_policy
from xpolicylab.policies import JitterRule, load_policy

PACK = Path(__file__).resolve().parents[1] / "recording" / "pack"
CHUNK = 4


@pytest.fixture(scope="module")
def queue(tmp_path_factory: pytest.TempPathFactory) -> list[PlannedEpisode]:
    from dojo.backends.mjx.cache import warp_installed

    if not warp_installed():
        pytest.skip("needs warp-lang (pip install 'robodojo[warp]'): MJX's jax implementation compiles for minutes")
    library = SpecLibrary.load([PACK], strict=False)
    suite = library.get("suite", "short_suite")
    return list(compile_suite(library, suite, tmp_path_factory.mktemp("plans"), episodes=3).episodes)


class _Asked:
    """A policy link that counts the chunks it was asked for, and keeps the privileged state of each observation
    it was given in `seen` (when given a list)."""

    def __init__(self, link: Any, seen: list[tuple[np.ndarray, np.ndarray]] | None = None) -> None:
        self.link, self.metadata, self.chunks, self.seen = link, link.metadata, 0, seen

    def reset(self, env_ids: Sequence[int]) -> None:
        self.link.reset(env_ids)

    def act(self, obs: Sequence[Any], env_ids: Sequence[int]) -> np.ndarray:
        self.chunks += len(env_ids)
        if self.seen is not None:
            self.seen.extend((o["privileged"]["qpos"], o["privileged"]["qvel"]) for o in obs)
        return self.link.act(obs, env_ids)

    def device_rule(self) -> Any:
        return self.link.device_rule()

    def image_buffers(self) -> Any:
        return self.link.image_buffers()

    def close(self) -> None:
        self.link.close()


def _run(queue: list[PlannedEpisode], policy: dict[str, Any], on_device: str, num_envs: int = 2,
         known: list[PlannedEpisode] | None = None, streams: bool = False,
         seen: list[tuple[np.ndarray, np.ndarray]] | None = None) -> tuple[dict[tuple, tuple], Any, int]:
    """`dojo run`'s loop on the mjx backend (`backend.streams` as given), which knows the plans of `known`
    (default: the queue's): each episode's result row (by key), the backend after the run and how many chunks the
    policy was asked for. With `seen` the backend is privileged and the list gets each observation's state.
    Buckets are not merged (`backend.merge=auto` would merge these few environments on streams, and a merged model's
    parked slots move the solver's last bits): the paths compared here differ in where the physics runs only."""
    link = _Asked(open_policy({"url": None, "chunk_size": CHUNK, **policy}, "arx_x5_bimanual"), seen)
    options = BackendOptions(settings={"impl": "warp", "streams": streams, "merge": False}, action_modes=("joint",),
                             plan_paths={item.plan_hash: str(item.plan_path) for item in known or queue},
                             privileged=seen is not None)
    built = []

    def factory() -> Any:
        built.append(make_backend("mjx", options))
        return built[-1]

    with ResultsStore(":memory:") as store:
        evaluate(queue, factory, link, store, "run", num_envs=num_envs, progress=Progress(len(queue), mode="quiet"),
                 on_device=on_device)
        rows = {r.key: (r.success, r.score, r.steps, r.stage_times, r.failure_reason, r.success_terms)
                for r in store.rows("run")}
    return rows, built[0], link.chunks


@pytest.fixture(scope="module")
def host_zero(queue) -> tuple[dict[tuple, tuple], Any, int]:
    """The zero policy on the host path, the jitted tick: what the other paths are held to."""
    return _run(queue, {"name": "zero"}, "off")


def test_zero_in_the_tick_records_what_the_host_path_records_bit_for_bit(queue, host_zero, caplog):
    host, host_backend, asked = host_zero
    with caplog.at_level(logging.INFO, logger="dojo.evaluation.evaluate"):
        device, device_backend, not_asked = _run(queue, {"name": "zero"}, "on")
    assert len(host) == 3 and all(steps == 6 for _, _, steps, *_ in host.values())
    assert device == host
    # the arms held the same poses through every chunk, and the refill compiled nothing: one program
    np.testing.assert_array_equal(device_backend.qpos(), host_backend.qpos())
    assert device_backend._engine.compilations() == 1
    assert asked == 3 * 2 and not_asked == 0  # two chunks per episode on the host, none asked on the device
    assert "policy zero runs on the device" in caplog.text


def test_physics_on_streams_records_what_the_jitted_tick_records_bit_for_bit(queue, host_zero):
    """`backend.streams=true` (`dojo run`'s engine with its physics on Warp's lanes between two jitted halves) with
    the backend's own predicates, observations and full forward after the physics: the same rows and poses."""
    host, host_backend, _ = host_zero
    split, split_backend, asked = _run(queue, {"name": "zero"}, "off", streams=True)
    assert split_backend._engine._physics is not None and split_backend._engine.compilations() == 1
    assert split == host and asked == 3 * 2
    np.testing.assert_array_equal(split_backend.qpos(), host_backend.qpos())


def test_the_privileged_state_on_streams_is_the_jitted_ticks(queue):
    """A privileged policy's state (qpos, qvel each observation) on streams is read from each bucket's words
    (`Engine.field`), not by unpacking every leaf: the same arrays, bit for bit, as on the jitted tick."""
    jitted, split = [], []
    _run(queue, {"name": "zero"}, "off", seen=jitted)
    _, split_backend, _ = _run(queue, {"name": "zero"}, "off", streams=True, seen=split)
    assert split_backend._engine._physics is not None and len(split) == len(jitted) == 3 * 2
    for (q, v), (q0, v0) in zip(split, jitted):
        np.testing.assert_array_equal(np.asarray(q), np.asarray(q0))
        np.testing.assert_array_equal(np.asarray(v), np.asarray(v0))
    assert split_backend._engine._unpack._cache_size() == 0


def test_random_in_the_tick_is_reproducible_from_its_seed_and_restarts_with_each_episode(queue):
    """An episode's draws and chunks depend on the seed and the episode alone: played in a slot that ran another
    episode first, it ends exactly as in a fresh backend (a chunk or a draw counter carried over would move the arms
    otherwise), and another seed moves the arms otherwise. Three runs, since each compiles a tick."""
    after, after_backend, asked = _run(queue[:2], {"name": "random", "seed": 3}, "on", num_envs=1)
    alone, alone_backend, _ = _run(queue[1:2], {"name": "random", "seed": 3}, "on", num_envs=1, known=queue[:2])
    _, other_backend, _ = _run(queue[:2], {"name": "random", "seed": 4}, "on", num_envs=1)
    assert asked == 0
    assert after[queue[1].plan_hash, queue[1].eval_seed, queue[1].episode] == next(iter(alone.values()))
    np.testing.assert_array_equal(after_backend.qpos(), alone_backend.qpos())
    assert np.abs(other_backend.qpos() - after_backend.qpos()).max() > 1e-4


def test_the_rule_is_the_same_arithmetic_under_jax():
    """What the tick traces (`jax.numpy`) is what the host computes (`numpy`): in bounds, grippers as drawn."""
    import jax.numpy as jnp

    rule = load_policy("random", {"max_delta": 0.3, "chunk_size": CHUNK}).device_rule()
    assert isinstance(rule, JitterRule)
    rng = np.random.default_rng(0)
    lo, hi = np.asarray(rule.lo, np.float32), np.asarray(rule.hi, np.float32)
    pose = rng.uniform(lo - 0.2, hi + 0.2, (256, len(lo))).astype(np.float32)  # some outside the bounds
    uniform = rng.random((256, rule.draws)).astype(np.float32)
    on_host = rule.row(np, pose, uniform)
    traced = np.asarray(rule.row(jnp, jnp.asarray(pose), jnp.asarray(uniform)))
    np.testing.assert_allclose(traced, on_host, rtol=0, atol=1e-6)
    assert traced.dtype == np.float32 and np.all((traced >= lo) & (traced <= hi))
    np.testing.assert_array_equal(traced[:, [6, 13]], uniform[:, -2:])


def test_a_backend_with_a_rule_takes_no_actions_and_takes_it_only_before_load():
    from dojo.backends.mjx.backend import MjxBackend

    backend = MjxBackend(impl="jax", action_modes=("joint",))
    backend.attach_rule(load_policy("zero", {}).device_rule())
    with pytest.raises(ValueError, match="a policy rule is attached.*step_with_rule"):
        backend.step(np.zeros((0, 14), np.float32))
    backend._engine = object()  # as after load
    with pytest.raises(RuntimeError, match="attach_rule before load"):
        backend.attach_rule(load_policy("zero", {}).device_rule())
    with pytest.raises(ValueError, match="no policy rule is attached"):
        MjxBackend(impl="jax").step_with_rule()
