"""The CPU path: MuJoCo's renderer behind the batched interface (the fallback and the mujoco backend's cameras)."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from dojo.backends.mjx.render import CAMERAS, CpuRenderer, RenderConfig
from dojo.backends.mujoco.backend import MujocoBackend
from dojo.backends.mujoco.render import render_cameras

W, H = 65, 49
"""Odd sizes put a pixel centre exactly on each camera's optical axis (pixel [24, 32])."""


@pytest.fixture(scope="module")
def renderer(standard_plan, random_plan):
    r = CpuRenderer([standard_plan.model(), random_plan.model()], RenderConfig(width=W, height=H, depth=True))
    yield r
    r.close()


def _arm_moved(plan, arm: str, offset: float = 0.4) -> np.ndarray:
    model = plan.model()
    qpos = np.asarray(plan.init_qpos, dtype=float).copy()
    for name in plan.robot["arm_joints"]:
        if name.startswith(arm):
            qpos[model.joint(name).qposadr[0]] += offset
    return qpos


def test_every_camera_at_the_configured_size(renderer, standard_plan, random_plan):
    frames = renderer.render([0, 1, 0], [np.asarray(standard_plan.init_qpos), np.asarray(random_plan.init_qpos),
                                         np.asarray(standard_plan.init_qpos)])
    assert frames.rgb.shape == (3, len(CAMERAS), H, W, 3) and frames.rgb.dtype == np.uint8
    assert frames.depth.shape == (3, len(CAMERAS), H, W) and frames.depth.dtype == np.uint16
    assert all(frames.rgb[0, k].std() > 5 for k in range(len(CAMERAS)))  # real pictures, not blank buffers
    np.testing.assert_array_equal(frames.rgb[0], frames.rgb[2])  # the same state renders the same


def test_the_wrist_camera_moves_with_its_arm(renderer, standard_plan):
    home = np.asarray(standard_plan.init_qpos)
    frames = renderer.render([0, 0], [home, _arm_moved(standard_plan, "left")])
    change = np.abs(frames.rgb[0].astype(int) - frames.rgb[1].astype(int)).mean(axis=(1, 2, 3))
    left, right = CAMERAS.index("left_wrist"), CAMERAS.index("right_wrist")
    assert change[left] > 10 * max(change[right], 0.5)
    assert np.abs(frames.depth[0, left].astype(int) - frames.depth[1, left].astype(int)).mean() > 20


def test_depth_is_planar_millimetres(renderer, standard_plan):
    """The optical-axis pixel's depth equals a MuJoCo ray cast's distance along the axis, and every pixel equals
    MuJoCo's own depth buffer in millimetres."""
    model = standard_plan.model()
    data = standard_plan.initial_data(model)
    frames = renderer.render([0], [np.asarray(standard_plan.init_qpos)])
    for k, cam in enumerate(CAMERAS):
        c = model.camera(cam).id
        axis = -data.cam_xmat[c].reshape(3, 3)[:, 2]
        geom = np.zeros(1, np.int32)
        dist = mujoco.mj_ray(model, data, data.cam_xpos[c], axis, np.array([1, 1, 1, 0, 0, 0], np.uint8), 1,
                             model.cam_bodyid[c], geom)  # the camera's own housing is behind the near plane
        assert dist > 0
        assert abs(int(frames.depth[0, k, H // 2, W // 2]) - 1000 * dist) <= 2.0, cam
    with mujoco.Renderer(model, height=H, width=W) as gl:
        gl.enable_depth_rendering()
        gl.update_scene(data, camera="head")
        metres = gl.render()
    np.testing.assert_array_equal(frames.depth[0, 0], np.round(metres * 1000).astype(np.uint16))


def test_random_setting_changes_what_it_should(renderer, standard_plan, random_plan):
    """Same task and seed: the random setting's lighting, background and table texture change the head image
    (background band above the table and the table top), while each setting alone renders deterministically."""
    scene_s, scene_r = standard_plan.scene, random_plan.scene
    assert (scene_s["lighting"], scene_s["background"], scene_s["table_texture"]) != \
        (scene_r["lighting"], scene_r["background"], scene_r["table_texture"])
    qs, qr = np.asarray(standard_plan.init_qpos), np.asarray(random_plan.init_qpos)
    frames = renderer.render([0, 1, 1], [qs, qr, qr])
    head = CAMERAS.index("head")
    std, rnd = frames.rgb[0, head].astype(int), frames.rgb[1, head].astype(int)
    np.testing.assert_array_equal(frames.rgb[1], frames.rgb[2])
    background = slice(0, H // 6)
    table = (slice(H // 2, 3 * H // 4), slice(W // 3, 2 * W // 3))
    assert np.abs(std[background] - rnd[background]).mean() > 8
    assert np.abs(std[table] - rnd[table]).mean() > 8


def test_the_cpu_backend_renders_only_the_cameras_asked_for(standard_plan):
    with MujocoBackend(num_threads=1, cameras=["left_wrist"], width=40, height=30, depth=True) as backend:
        backend.load([standard_plan])
        (obs,) = backend.reset()
    assert set(obs["images"]) == {"left_wrist"} and obs["images"]["left_wrist"].shape == (30, 40, 3)
    assert obs["depth"]["left_wrist"].shape == (30, 40) and obs["depth"]["left_wrist"].dtype == np.uint16
    reference = render_cameras(standard_plan.model(), standard_plan.initial_data(), ["left_wrist"], 40, 30)
    np.testing.assert_array_equal(obs["images"]["left_wrist"], reference["left_wrist"])
