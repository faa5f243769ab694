"""The batched renderer (MuJoCo Warp's ray tracer): images per environment and camera, per-environment colours,
cameras that move with the arms. It runs wherever warp-lang is installed: on an NVIDIA GPU, or on Warp's CPU device
(`./setup.sh` installs it, so CI runs these on the CPU). Parity with MuJoCo at full size, per task and setting:
`python -m dojo.backends.mjx.render_parity`.
"""

from __future__ import annotations

import numpy as np
import pytest
from dojo.backends.mjx.cache import warp_installed
from dojo.backends.mjx.render import CAMERAS, RenderConfig


@pytest.fixture(scope="module")
def warp_ready():
    if not warp_installed():
        pytest.skip("needs warp-lang (pip install 'robodojo[warp]')")


def test_batched_images_follow_state_and_per_env_colours(warp_ready, standard_plan):
    import jax
    import jax.numpy as jnp
    from dojo.backends.mjx.render import WarpRenderer
    from dojo.backends.mjx.render_parity import moved_qpos
    from mujoco import mjx

    model = standard_plan.model()
    home = np.asarray(standard_plan.init_qpos)
    states = np.stack([home, moved_qpos(standard_plan, model), home])
    mx = mjx.put_model(model, impl="warp")
    data = jax.vmap(lambda q: mjx.make_data(model, impl="warp", naconmax=3, njmax=1).replace(qpos=q))(
        jnp.asarray(states, jnp.float32))
    data = jax.jit(jax.vmap(mjx.kinematics, in_axes=(None, 0)))(mx, data)
    rgba = np.repeat(model.geom_rgba[None], 3, axis=0)
    rgba[2, :, :3] = [1.0, 0.0, 1.0]  # env 2: every geom magenta
    batched = mx.tree_replace({"geom_rgba": jnp.asarray(rgba, mx.geom_rgba.dtype)})
    in_axes = jax.tree.map(lambda _: None, mx).tree_replace({"geom_rgba": 0})
    renderer = WarpRenderer(model, 3, RenderConfig(width=64, height=48, depth=True))
    frames = jax.jit(lambda m, d: renderer(m, d, in_axes))(batched, data)
    rgb, depth = np.asarray(frames.rgb), np.asarray(frames.depth)
    assert rgb.shape == (3, len(CAMERAS), 48, 64, 3) and depth.shape == (3, len(CAMERAS), 48, 64)
    assert rgb[0].std() > 5 and (depth[0] > 0).mean() > 0.9
    left = CAMERAS.index("left_wrist")
    assert np.abs(rgb[0, left].astype(int) - rgb[1, left].astype(int)).mean() > 10
    assert np.abs(rgb[0].astype(int) - rgb[2].astype(int)).mean() > 10
    np.testing.assert_array_equal(depth[0], depth[2])


def test_the_mjx_backend_renders_its_observations_on_the_device(warp_ready, standard_plan, random_plan):
    """`dojo run backend=mjx` on Warp: observations carry images from the engine's own state on the GPU, for the
    slots observed, each slot its own member's scene (the random setting's colours differ from the standard)."""
    from dojo.backends.mjx.backend import MjxBackend
    from dojo.backends.mjx.device_cameras import BucketCameras

    # joint actions only: the ee modes' IK would be most of the tick's XLA program (minutes on a cold cache)
    backend = MjxBackend(impl="warp", cameras=CAMERAS, width=64, height=48, depth=True, action_modes=("joint",))
    backend.load([standard_plan, random_plan, standard_plan])
    assert backend._renderers and all(isinstance(r, BucketCameras) for r in backend._renderers)
    first = backend.reset()
    for obs in first:
        assert set(obs["images"]) == set(CAMERAS) and set(obs["depth"]) == set(CAMERAS)
        head = obs["images"]["head"]
        assert head.shape == (48, 64, 3) and head.dtype == np.uint8 and head.std() > 5
        assert obs["depth"]["head"].dtype == np.uint16 and (obs["depth"]["head"] > 0).mean() > 0.9
    np.testing.assert_array_equal(first[0]["images"]["head"], first[2]["images"]["head"])
    assert np.abs(first[0]["images"]["head"].astype(int) - first[1]["images"]["head"].astype(int)).mean() > 1
    joints = first[0]["state"]["joint_pos"].copy()
    joints[:3] += 0.4  # the left arm turns: its wrist camera sees another view
    for _ in range(5):  # 0.2 s of control: the arm is well on its way
        moved = backend.step(np.tile(joints, (3, 1)), observe=[0])
    assert "images" in moved.obs[0] and "images" not in moved.obs[1]
    left = moved.obs[0]["images"]["left_wrist"].astype(int)
    assert np.abs(left - first[0]["images"]["left_wrist"].astype(int)).mean() > 5
