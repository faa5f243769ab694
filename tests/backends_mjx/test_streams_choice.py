"""`backend.streams=auto`: where the tick's physics goes on streams, decided without starting CUDA first and then by
the backend on the device it got."""

from __future__ import annotations

import os

import pytest

from dojo.backends.mjx import ENGINE_STREAMS_ENVIRONMENT, nvidia_devices, streams_may_run
from dojo.backends.mjx.cache import choose_streams


def test_auto_runs_streams_only_for_mujoco_warp_on_a_gpu_without_cameras() -> None:
    assert choose_streams("auto", "warp", on_gpu=True, cameras=False) == (True, "auto: MuJoCo Warp on a GPU, no cameras")
    assert choose_streams("auto", "warp", on_gpu=False, cameras=False)[0] is False  # Warp's CPU device
    assert choose_streams("auto", "jax", on_gpu=True, cameras=False)[0] is False
    off, why = choose_streams("auto", "warp", on_gpu=True, cameras=True)
    assert off is False and "cameras" in why
    assert choose_streams(True, "warp", on_gpu=False, cameras=True) == (True, "as set")  # asked for: as asked
    assert choose_streams(False, "warp", on_gpu=True, cameras=False) == (False, "as set")


def test_nvidia_devices_are_counted_from_the_driver_nodes_within_cuda_visible_devices(tmp_path) -> None:
    for name in ("nvidia0", "nvidia1", "nvidiactl", "nvidia-uvm", "nvidia-modeset"):
        (tmp_path / name).touch()
    assert nvidia_devices(tmp_path, {}) == 2
    assert nvidia_devices(tmp_path, {"CUDA_VISIBLE_DEVICES": "1"}) == 1
    assert nvidia_devices(tmp_path, {"CUDA_VISIBLE_DEVICES": "0,1,2"}) == 2
    assert nvidia_devices(tmp_path, {"CUDA_VISIBLE_DEVICES": ""}) == 0
    assert nvidia_devices(tmp_path, {"CUDA_VISIBLE_DEVICES": "-1"}) == 0
    assert nvidia_devices(tmp_path / "none", {}) == 0


def test_auto_is_ruled_out_before_cuda_for_jax_cameras_or_no_gpu() -> None:
    assert not streams_may_run("jax", ())
    assert not streams_may_run("warp", ("head",))
    if nvidia_devices() == 0:
        assert not streams_may_run("auto", ())


@pytest.mark.skipif(nvidia_devices() > 0, reason="checks a machine without an NVIDIA GPU")
def test_a_default_mjx_backend_on_a_cpu_keeps_the_jitted_tick_and_the_environment(monkeypatch, caplog) -> None:
    """The default `backend.streams=auto` on a machine without a GPU: the physics stays in the jitted tick, the log
    says why, and nothing of the streams' environment is set for the process."""
    import logging

    from dojo.backends.mjx import make
    from dojo.backends.mjx.backend import MjxBackend
    from dojo.backends.mjx.cache import warp_installed
    from dojo.backends.registry import BackendOptions

    for name in ENGINE_STREAMS_ENVIRONMENT:
        monkeypatch.delenv(name, raising=False)
    assert make(BackendOptions(settings={"streams": "auto"})).streams is False
    assert not set(ENGINE_STREAMS_ENVIRONMENT) & set(os.environ)
    if warp_installed():  # MuJoCo Warp on Warp's CPU device: auto decides in the backend, and says so
        with caplog.at_level(logging.INFO, logger="dojo.backends.mjx.backend"):
            assert MjxBackend(impl="warp", streams="auto").streams is False
        assert "physics in the jitted tick (backend.streams=auto: MuJoCo Warp is not on a GPU here)" in caplog.text


def test_a_streams_setting_other_than_true_false_or_auto_is_refused_by_name() -> None:
    from dojo.backends.mjx import make
    from dojo.backends.registry import BackendOptions

    with pytest.raises(ValueError, match="backend.streams takes true, false or auto, not 'maybe'"):
        make(BackendOptions(settings={"streams": "maybe"}))
