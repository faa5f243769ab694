"""The GPU path's pieces that need no GPU: pixel unpacking, millimetres, camera and light poses, set-up checks."""

from __future__ import annotations

import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from dojo.backends.mjx import render as R


def _pack(rgb: np.ndarray) -> np.ndarray:
    """uint8 [..., 3] -> uint32 as the warp renderer packs it (blue low byte, then green, red, alpha 255)."""
    r, g, b = (rgb[..., k].astype(np.uint32) for k in range(3))
    return b | (g << 8) | (r << 16) | (np.uint32(255) << 24)


def test_unpack_rgb_contiguous_cameras():
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, size=(2, 3, 4, 5, 3), dtype=np.uint8)  # [B, C, H, W, 3]
    packed = _pack(images).reshape(2, -1)
    out = np.asarray(R.unpack_rgb(packed, R.PixelLayout.contiguous(3, 5, 4, depth=False)))
    assert out.dtype == np.uint8
    np.testing.assert_array_equal(out, images)


def test_unpack_rgb_follows_the_addresses():
    """Cameras need not be stored in order or back to back: each is cut at its own address."""
    rng = np.random.default_rng(1)
    a, b = (rng.integers(0, 256, size=(2, 3, 3), dtype=np.uint8) for _ in range(2))
    flat = np.concatenate([np.zeros(4, np.uint32), _pack(b).ravel(), _pack(a).ravel()])
    layout = R.PixelLayout(width=3, height=2, rgb_adr=(10, 4), depth_adr=())
    out = np.asarray(R.unpack_rgb(flat[None], layout))[0]
    np.testing.assert_array_equal(out[0], a)
    np.testing.assert_array_equal(out[1], b)


def test_depth_to_mm_rounds_keeps_misses_and_saturates():
    metres = np.array([0.0, 0.0004, 0.0006, 1.2344, 1.2346, 70.0], np.float32)
    mm = np.asarray(R.depth_to_mm(metres))
    assert mm.dtype == np.uint16
    assert mm.tolist() == [0, 0, 1, 1234, 1235, R.MAX_DEPTH_MM]


def test_unpack_depth_per_camera():
    depth = np.arange(2 * 2 * 3 * 4, dtype=np.float32).reshape(2, 2, 3, 4) / 100.0  # [B, C, H, W] metres
    layout = R.PixelLayout.contiguous(2, 4, 3, depth=True)
    mm = np.asarray(R.unpack_depth(depth.reshape(2, -1), layout))
    np.testing.assert_array_equal(mm, np.round(depth * 1000).astype(np.uint16))


def test_cpu_depth_marks_the_far_plane_as_no_hit(standard_plan):
    model = standard_plan.model()
    far = model.vis.map.zfar * model.stat.extent
    mm = R.cpu_depth_mm(np.array([[0.5, far]], np.float32), model)
    assert mm.tolist() == [[500, 0]]


def _moved_data(plan, seed: int) -> tuple[mujoco.MjModel, mujoco.MjData]:
    model = plan.model()
    data = plan.initial_data(model)
    rng = np.random.default_rng(seed)
    for name in plan.robot["arm_joints"]:
        data.qpos[model.joint(name).qposadr[0]] += rng.uniform(-0.5, 0.5)
    mujoco.mj_forward(model, data)
    return model, data


def test_camera_poses_match_mujoco_after_the_arms_move(standard_plan):
    model, data = _moved_data(standard_plan, 0)
    ids = R.camera_ids(model, R.CAMERAS)
    pos, mat = R.fixed_camera_poses(jnp.asarray(data.xpos), jnp.asarray(data.xmat), model.cam_bodyid[ids],
                                    jnp.asarray(model.cam_pos[ids]), jnp.asarray(model.cam_quat[ids]))
    np.testing.assert_allclose(np.asarray(pos), data.cam_xpos[ids], atol=1e-6)
    np.testing.assert_allclose(np.asarray(mat).reshape(-1, 9), data.cam_xmat[ids], atol=1e-6)


def test_light_poses_match_mujoco(random_plan):
    model, data = _moved_data(random_plan, 1)
    assert model.nlight > 0
    pos, direction = R.fixed_light_poses(jnp.asarray(data.xpos), jnp.asarray(data.xmat), model.light_bodyid,
                                         jnp.asarray(model.light_pos), jnp.asarray(model.light_dir))
    np.testing.assert_allclose(np.asarray(pos), data.light_xpos, atol=1e-6)
    np.testing.assert_allclose(np.asarray(direction), data.light_xdir, atol=1e-6)


def test_camera_ids_name_the_missing_camera(standard_plan):
    with pytest.raises(ValueError, match="chest"):
        R.camera_ids(standard_plan.model(), ["head", "chest"])


def test_render_config_rejects_bad_sizes_and_repeats():
    with pytest.raises(ValueError):
        R.RenderConfig(width=0)
    with pytest.raises(ValueError):
        R.RenderConfig(cameras=("head", "head"))


def test_observation_images_follow_design_section_4():
    rgb = np.zeros((2, 3, 4, 5, 3), np.uint8)
    rgb[1, 2] = 7
    depth = np.ones((2, 3, 4, 5), np.uint16)
    obs = R.observation_images(R.Frames(rgb, depth), R.CAMERAS)
    assert len(obs) == 2 and set(obs[0]) == {"images", "depth"}
    assert set(obs[1]["images"]) == set(R.CAMERAS)
    assert obs[1]["images"]["right_wrist"].shape == (4, 5, 3) and obs[1]["images"]["right_wrist"][0, 0, 0] == 7
    assert obs[0]["depth"]["head"].dtype == np.uint16
    assert "depth" not in R.observation_images(R.Frames(rgb, None), R.CAMERAS)[0]


def test_without_a_gpu_auto_renders_with_mujoco_and_warp_is_never_a_silent_fallback(standard_plan):
    from dojo.backends.mjx.cache import warp_installed

    ok, why = R.warp_renderer_available()
    if ok:
        pytest.skip("this machine can run the batched renderer")
    assert why
    renderer = R.make_renderer([standard_plan.model()], 1, R.RenderConfig(width=32, height=24))
    try:
        assert isinstance(renderer, R.CpuRenderer)
    finally:
        renderer.close()
    if warp_installed():  # asked for, the ray tracer runs on Warp's CPU device
        assert isinstance(R.make_renderer([standard_plan.model()], 1, R.RenderConfig(), impl="warp"), R.WarpRenderer)
    else:
        with pytest.raises(RuntimeError, match="warp-lang"):
            R.make_renderer([standard_plan.model()], 1, R.RenderConfig(), impl="warp")


def test_near_clipped_geoms_are_the_wrist_housings(standard_plan):
    """MuJoCo's near plane hides each wrist camera's own housing; the head camera loses nothing."""
    model = standard_plan.model()
    hidden = {c: R.near_clipped_geoms(model, model.camera(c).id) for c in R.CAMERAS}
    assert hidden["head"] == ()
    for side in ("left", "right"):
        geoms = hidden[f"{side}_wrist"]
        assert geoms and all(model.body(model.geom_bodyid[g]).id == model.cam_bodyid[model.camera(f"{side}_wrist").id]
                             for g in geoms)
