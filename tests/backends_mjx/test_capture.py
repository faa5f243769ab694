"""What keeps Warp's CUDA graph captures safe, checked on any machine: which ticks may capture, the garbage
collector held back and given back, and the graph mode `dojo run` uses by default."""

from __future__ import annotations

import gc
from pathlib import Path

import jax.numpy as jnp
import pytest
import yaml

from dojo.backends.mjx.batch import may_capture
from dojo.backends.mjx.cache import DEFAULT_GRAPH_MODE, GRAPH_MODES
from dojo.backends.mjx.capture import collector_held, run_settled


def test_only_warp_ticks_capture_and_the_staged_modes_only_on_the_first():
    assert not any(may_capture("jax", mode, tick) for mode in GRAPH_MODES for tick in (0, 1, 5))
    assert not may_capture("warp", "none", 0)
    for mode in ("warp_staged", "warp_staged_ex", "jax"):
        assert may_capture("warp", mode, 0) and not may_capture("warp", mode, 1)
    assert may_capture("warp", "warp", 0) and may_capture("warp", "warp", 7)


def test_the_collector_is_held_for_the_block_and_given_back_as_it_was():
    assert gc.isenabled()
    with collector_held():
        assert not gc.isenabled()
    assert gc.isenabled()
    with pytest.raises(RuntimeError):
        with collector_held():
            raise RuntimeError("a failed capture")
    assert gc.isenabled()
    gc.disable()
    try:
        with collector_held():
            pass
        assert not gc.isenabled()  # a caller that held it already keeps it held
    finally:
        gc.enable()


def test_a_settled_call_returns_its_results_computed():
    out = run_settled(lambda x: {"y": x * 2}, jnp.arange(3))
    assert out["y"].is_ready() and out["y"].tolist() == [0, 2, 4] and gc.isenabled()


def test_dojo_run_uses_the_default_graph_mode():
    config = Path(__file__).parents[2] / "dojo" / "cli" / "config" / "backend" / "mjx.yaml"
    assert yaml.safe_load(config.read_text())["graph_mode"] == DEFAULT_GRAPH_MODE
    assert DEFAULT_GRAPH_MODE in GRAPH_MODES
