"""The parity script's measures and the bench's set-up helpers (no GPU needed)."""

from __future__ import annotations

import numpy as np
from dojo.backends.mjx import render_parity as P
from dojo.backends.mjx.render import CAMERAS
from dojo.bench.render_bench import STANDARD_SIZES, _arm_mask, _split, render_grid


def test_ssim_and_mae_separate_same_from_different():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, size=(40, 50, 3), dtype=np.uint8)
    assert P.ssim(a, a) == 1.0 and P.rgb_mae(a, a) == 0.0
    noisy = np.clip(a.astype(int) + rng.integers(-3, 4, size=a.shape), 0, 255).astype(np.uint8)
    other = rng.integers(0, 256, size=a.shape, dtype=np.uint8)
    assert P.ssim(a, noisy) > 0.9
    assert P.ssim(a, other) < 0.1
    assert P.rgb_mae(a, noisy) < 2
    assert P.rgb_mae(a, other) > 50


def test_psnr_is_infinite_like_for_equal_images_and_falls_with_noise():
    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, size=(40, 50, 3), dtype=np.uint8)
    assert P.psnr(a, a) == 99.0
    off_by_one = (a.astype(int) ^ 1).astype(np.uint8)  # every channel off by exactly 1: MSE 1, 48.13 dB
    assert abs(P.psnr(a, off_by_one) - 20 * np.log10(255)) < 1e-9
    assert P.psnr(a, rng.integers(0, 256, size=a.shape, dtype=np.uint8)) < 10


def test_block_mean_removes_grain_finer_than_its_blocks_but_keeps_shading():
    grain = np.tile(np.array([[0, 255], [255, 0]], np.uint8), (8, 8))[..., None].repeat(3, axis=2)  # 16x16
    flat = np.full_like(grain, 127)
    assert P.psnr(grain, flat) < 10 and P.psnr(P.block_mean(grain), P.block_mean(flat)) > 50
    darker = (grain // 2).astype(np.uint8)  # a shading difference is still there after averaging
    assert P.psnr(P.block_mean(grain), P.block_mean(darker)) < 20
    assert P.block_mean(np.zeros((10, 9, 3)), 4).shape == (2, 2, 3)


def test_depth_stats_only_count_pixels_both_hit():
    a = np.array([[1000, 0, 2000, 3000]], np.uint16)
    b = np.array([[1001, 500, 0, 3050]], np.uint16)
    stats = P.depth_stats(a, b, within_mm=10)
    assert stats == {"median_mm": 25.5, "within_fraction": 0.5, "hit_fraction": 0.5}


def test_judge_names_each_missed_threshold():
    good = {"rgb_mae": 1.0, "ssim": 0.99, "depth": {"median_mm": 0.0, "within_fraction": 1.0}}
    assert P.judge(good) == []
    bad = {"rgb_mae": 40.0, "ssim": 0.2, "depth": {"median_mm": 9.0, "within_fraction": 0.5}}
    assert len(P.judge(bad)) == 4


def test_moved_state_turns_only_the_arm_joints(standard_plan):
    model = standard_plan.model()
    home = np.asarray(standard_plan.init_qpos)
    moved = P.moved_qpos(standard_plan, model)
    arm = {model.joint(n).qposadr[0] for n in standard_plan.robot["arm_joints"]}
    changed = set(np.flatnonzero(~np.isclose(home, moved)).tolist())
    assert changed and changed <= arm


def test_mujoco_reference_images_and_saved_batched_round_trip(standard_plan, tmp_path):
    states = P.plan_states(standard_plan)
    rgb, depth = zip(*(P.mujoco_images(standard_plan.model(), q, CAMERAS, 32, 24, plain=True) for q in states))
    rgb, depth = np.stack(rgb), np.stack(depth)
    P.save_batched(standard_plan, rgb, depth, tmp_path)
    back_rgb, back_depth = P.load_batched(standard_plan, tmp_path)
    np.testing.assert_array_equal(back_rgb, rgb)
    np.testing.assert_array_equal(back_depth, depth)
    rows = P.compare_plan(standard_plan, rgb, depth, 32, 24, tmp_path)
    assert len(rows) == 2 * len(CAMERAS) and not any(r["misses"] for r in rows)
    assert (tmp_path / f"{P.plan_label(standard_plan)}.png").exists()
    summary = P.summarize(rows, 1, 32, 24)
    assert summary["failed"] == 0 and summary["mean_psnr_db"] == 99.0
    assert summary["by_task_setting"] == {standard_plan.task: {standard_plan.setting: {
        "psnr_db": 99.0, "psnr_db_4x4": 99.0, "ssim": 1.0, "rgb_mae": 0.0, "images": 2 * len(CAMERAS)}}}


def test_bench_grid_and_split():
    grid = render_grid({"width": 320, "height": 240})
    assert {(w, h) for w, h, _ in grid} == set(STANDARD_SIZES) | {(320, 240)}
    assert {d for *_, d in grid} == {False, True}
    assert len(render_grid({"width": 640, "height": 480})) == 2 * len(STANDARD_SIZES)
    assert _split(10, 3) == [4, 3, 3] and _split(2, 4) == [1, 1, 1, 1]


def test_arm_mask_marks_the_arm_joints(standard_plan):
    from dojo.backends.mjx.bucket import make_buckets

    (bucket,) = make_buckets([standard_plan])
    mask = _arm_mask(bucket)
    assert mask.sum() == len(standard_plan.robot["arm_joints"])
