"""The emulator's cameras render the emulated world as it is now, and a dropped frame repeats the last one."""

from __future__ import annotations

import time

import numpy as np


def _move_left_arm(rig) -> None:
    with rig.sim.lock:  # controller calls from outside the emulator's thread take its lock
        rig.sim.set_joint_target(0, rig.sim.index.arm_q(rig.sim.data)[0] + 0.4, 1.0)
    end = time.monotonic() + 5.0
    while np.abs(rig.sim.arm_joints()[0] - rig.sim.arm_joints()[1]).max() < 0.3 and time.monotonic() < end:
        time.sleep(0.01)


def test_frames_follow_the_world(make_rig) -> None:
    rig = make_rig()
    cameras = rig.emulated.cameras(["head"], 64, 48)
    try:
        before = cameras.frames()["head"]
        _move_left_arm(rig)
        after = cameras.frames()["head"]
        assert before.shape == (48, 64, 3) and before.dtype == np.uint8
        assert np.abs(after.astype(int) - before.astype(int)).max() > 30 and cameras.dropped == 0
    finally:
        cameras.close()


def test_a_dropped_frame_repeats_the_last_one(make_rig) -> None:
    rig = make_rig(camera_drop=1.0)
    cameras = rig.emulated.cameras(["head", "right_wrist"], 64, 48)
    try:
        first = cameras.frames()  # nothing to repeat yet: rendered
        _move_left_arm(rig)
        again = cameras.frames()
        assert all(np.array_equal(first[c], again[c]) for c in ("head", "right_wrist"))
        assert cameras.dropped == 2
    finally:
        cameras.close()
