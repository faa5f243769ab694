"""`BucketCameras`' plumbing on any machine: each row rendered from its own member's model fields and its own state,
only the rows asked for returned, in the order asked. MuJoCo Warp's renderer runs only on an NVIDIA GPU, so here a
stand-in paints each world's image from what it was given; the real renderer inside the backend is tested by
`tests/render/test_warp_render.py` (`-m gpu`)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import toy_plan

from dojo.backends.mjx import device_cameras
from dojo.backends.mjx.batch import Engine
from dojo.backends.mjx.bucket import make_buckets
from dojo.backends.mjx.render import Frames, RenderConfig

SIZES = (0.02, 0.03, 0.04)
"""Block half-sizes of the three members: a varying model field (`geom_size`)."""


class _Painter:
    """Stands in for `WarpRenderer`: pixel (0, 0) of camera 0 carries the block's size in mm, pixel (0, 1) the
    slider's position in mm, depth the world's index in the batch."""

    def __init__(self, model, nworld, config):
        self.config, self.block = config, model.geom("block/g0").id

    def __call__(self, m, data, in_axes):
        b = data.qpos.shape[0]
        rgb = jnp.zeros((b, len(self.config.cameras), self.config.height, self.config.width, 3), jnp.uint8)
        rgb = rgb.at[:, 0, 0, 0, 0].set(jnp.round(m.geom_size[:, self.block, 0] * 1000).astype(jnp.uint8))
        rgb = rgb.at[:, 0, 0, 1, 0].set(jnp.round(data.qpos[:, 0] * 1000 + 100).astype(jnp.uint8))
        depth = jnp.broadcast_to(jnp.arange(b, dtype=jnp.uint16)[:, None, None, None],
                                 (b, len(self.config.cameras), self.config.height, self.config.width))
        return Frames(rgb, depth)


@pytest.fixture(scope="module")
def engine():
    bucket, = make_buckets([toy_plan(seed=0, block_size=s) for s in SIZES])
    assert "geom_size" in bucket.varying
    return Engine([bucket], [4], "jax")


def test_rows_render_their_own_member_and_state_and_only_those_asked(engine, monkeypatch):
    monkeypatch.setattr(device_cameras, "WarpRenderer", _Painter)
    arr = engine.arrays[0]
    cameras = device_cameras.BucketCameras(arr, RenderConfig(cameras=("head", "left_wrist"), width=4, height=3,
                                                             depth=True))
    members = np.asarray([2, 0, 1, 2], np.int32)
    on, off = [np.ones(4, bool)], [np.zeros(4, bool)]
    ctrl = [np.asarray([[0.0], [0.1], [0.0], [-0.1]], np.float32)]
    engine.tick([members], on, off, ctrl)
    for _ in range(3):
        engine.tick([members], off, on, ctrl)
    slider = np.asarray(engine.data[0].qpos)[:, 0]
    frames = cameras.frames(engine.data[0], members, [3, 1])
    assert frames.rgb.shape == (2, 2, 3, 4, 3) and frames.depth.shape == (2, 2, 3, 4)
    assert isinstance(frames.rgb, np.ndarray)
    np.testing.assert_array_equal(frames.rgb[:, 0, 0, 0, 0], [40, 20])  # members 2 and 0: blocks of 40 and 20 mm
    np.testing.assert_array_equal(frames.rgb[:, 0, 0, 1, 0], np.round(slider[[3, 1]] * 1000 + 100).astype(np.uint8))
    assert slider[1] > slider[0] > slider[3]  # the rows were driven apart, so a row mix-up would show
    np.testing.assert_array_equal(frames.depth[:, 0, 0, 0], [3, 1])
    # Each camera's images of the rows asked for lie one after another on the host (one array per camera for the
    # policy link, `xpolicylab.columns.Rows.runs`), handed back as a [rows, cameras, ...] view.
    assert np.swapaxes(frames.rgb, 0, 1).flags.c_contiguous and np.swapaxes(frames.depth, 0, 1).flags.c_contiguous


def test_the_render_bench_loop_runs_with_the_arms_moved_by_kinematics(monkeypatch):
    """`dojo bench render physics=false`: the arms move along a wave by kinematics alone, the cameras render every
    bucket each tick, and a row per size reports its rates (the stand-in painter for MuJoCo Warp's renderer)."""
    from dojo.backends.mjx import render
    from dojo.bench.render_bench import measure_batched
    from dojo.compiler.plan import compile_plan
    from dojo.compiler.spec_library import SpecLibrary

    library = SpecLibrary.load([])
    plans = [compile_plan(library, library.get("task", "stack_blocks"), "standard", 0)]
    class Blank:  # renders black frames of the asked size, one per world and camera
        def __init__(self, model, nworld, config):
            self.config = config

        def __call__(self, m, data, in_axes):
            shape = (data.qpos.shape[0], len(self.config.cameras), self.config.height, self.config.width)
            return Frames(jnp.zeros((*shape, 3), jnp.uint8), None)

    monkeypatch.setattr(render, "WarpRenderer", Blank)
    result = measure_batched(plans, 2, 1, [(4, 3, False)], impl="jax", physics=False)
    row, = result["rows"]
    assert result["physics"] is False and result["envs"] == 2 and (row["width"], row["height"]) == (4, 3)
    assert row["interactions_per_s"] > 0 and row["render_frames_per_s"] > 0
