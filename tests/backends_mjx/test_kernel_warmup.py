"""The ahead-of-time kernel warm-up (`kernel_warmup`): settings, and compiling recorded variants side by side with
failures reported (stand-ins for the compiler, any machine); with warp-lang, a variant compiled ahead is the one a
launch loads (Warp's CPU device)."""

from __future__ import annotations

import importlib.util
import threading
from types import SimpleNamespace

import pytest
from conftest import toy_plan

from dojo.backends.mjx.kernel_warmup import compile_all, thread_count, warm_kernels


def test_thread_count_reads_the_setting():
    assert thread_count(0) == 0 and thread_count(None) == 0 and thread_count("3") == 3
    assert thread_count("auto") >= 1
    for bad in ("many", -1):
        with pytest.raises(ValueError, match="kernel_threads"):
            thread_count(bad)


def test_off_means_nothing_is_recorded_or_compiled():
    warm = warm_kernels([SimpleNamespace(key="never looked at")], 0)
    assert warm.threads == 0 and warm.modules == 0 and warm.seconds == 0.0


def _launches(n: int) -> dict:
    return {(f"m{k}", None): (SimpleNamespace(name=f"m{k}"), None) for k in range(n)}


def test_variants_compile_side_by_side_and_failures_are_reported():
    barrier = threading.Barrier(3, timeout=10)  # three compiles must be running at once

    def compile_one(module, block, device):
        if module.name == "m3":
            raise RuntimeError("nvrtc error")
        if module.name in ("m0", "m1", "m2"):
            barrier.wait()
        return module.name != "m4"  # m4 was in the cache already

    warm = compile_all(_launches(5), 3, "cuda:0", compile_one)
    assert warm.modules == 5 and warm.compiled == 3 and warm.threads == 3
    assert warm.failed == {"m3@None": "RuntimeError: nvrtc error"}
    assert warm.figures()["failed"] == warm.failed


@pytest.mark.skipif(importlib.util.find_spec("warp") is None, reason="needs warp-lang")
def test_a_variant_compiled_ahead_is_the_one_a_launch_loads(tmp_path, monkeypatch):
    import warp as wp

    from dojo.backends.mjx.bucket import make_buckets
    from dojo.backends.mjx.kernel_warmup import compile_variant
    from dojo.backends.mjx.warp_launches import recorded_launches
    from warp._src.context import _resolve_launch_block_dim

    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
    wp.init()
    device = wp.get_device("cpu")
    launches = recorded_launches(make_buckets([toy_plan()])[0], device)
    (module, block), = [v for k, v in sorted(launches.items()) if "__locals__" in k[0]][:1]
    assert compile_variant(module, block, device) is True
    assert compile_variant(module, block, device) is False  # found in the cache
    before = sorted(p.name for p in tmp_path.rglob("*"))
    module.load(device, _resolve_launch_block_dim(device, block))  # what wp.launch does first
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing compiled again
