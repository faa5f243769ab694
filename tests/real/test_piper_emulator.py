"""The unmodified piper-sdk drives the emulated PiPER over python-can virtual buses (one per arm).

Checked: the SDK reads the emulated joints and gripper; joint and gripper commands move the emulated arms;
the firmware's rules (no motion before enable and CAN/MOVE J mode, nothing after a quick stop until resumed);
the emulator's imperfections (encoder noise, command delay, dropped feedback frames). The command-to-motion
round trip is measured and reported as a figure, not asserted.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

pytest.importorskip("can")
piper_sdk = pytest.importorskip("piper_sdk")

from dojo.backends.real.piper_driver import PiperDriver  # noqa: E402

RESOLUTION = 1e-5  # rad: the wire carries 0.001 degree (1.7e-5 rad); rounding is half of that


def _connect(rig) -> PiperDriver:
    driver = PiperDriver(rig.robot, rig.channels, interface="virtual")
    driver.connect()
    return driver


def _wait(condition, timeout: float = 5.0) -> bool:
    """Poll `condition` until it holds; False if it never does within `timeout` (a failure, not a timing)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.002)
    return False


def test_sdk_reads_the_emulated_joints_and_grippers(make_rig) -> None:
    rig = make_rig()
    with _connect(rig) as driver:
        state = driver.read()
        assert np.abs(state.joint_pos - rig.sim.arm_joints()).max() < RESOLUTION
        home_q, home_grip = driver.home_pose
        assert np.abs(state.joint_pos - home_q).max() < 1e-3
        assert np.allclose(state.gripper, home_grip, atol=0.02)
        assert state.stamp > 0


def test_joint_and_gripper_commands_move_the_emulated_arms(make_rig) -> None:
    rig = make_rig()
    with _connect(rig) as driver:
        start = driver.read()
        target = start.joint_pos + np.array([[0.2, 0.1, -0.1, 0.2, -0.2, 0.3], [-0.2, 0.15, -0.15, -0.2, 0.2, -0.3]])
        driver.command(target, np.array([0.3, 0.6]))
        assert _wait(lambda: np.abs(rig.sim.arm_joints() - target).max() < 2e-3), rig.sim.arm_joints() - target
        assert _wait(lambda: np.abs(driver.read().joint_pos - target).max() < 2e-3)
        assert _wait(lambda: np.allclose(driver.read().gripper, [0.3, 0.6], atol=0.02)), driver.read().gripper


def test_round_trip_command_to_observed_motion(make_rig, figures) -> None:
    """Time from the SDK's joint command to the first SDK joint reading that moved (20 commands)."""
    rig = make_rig()
    with _connect(rig) as driver:
        trips = []
        for k in range(20):
            before = driver.read().joint_pos
            target = before.copy()
            target[:, 0] += 0.05 if k % 2 == 0 else -0.05
            sent = time.monotonic()
            driver.command(target, driver.read().gripper)
            assert _wait(lambda: np.abs(driver.read().joint_pos[:, 0] - before[:, 0]).min() > 5 * RESOLUTION)
            trips.append(time.monotonic() - sent)
            time.sleep(0.05)
        ms = np.asarray(trips) * 1000.0
        figures.add("piper_emulator.round_trip_ms", {"p50": round(float(np.median(ms)), 2),
                                                     "p90": round(float(np.percentile(ms, 90)), 2),
                                                     "max": round(float(ms.max()), 2), "n": len(ms)})


@pytest.mark.filterwarnings("ignore:The 'bustype' argument is deprecated:DeprecationWarning")
def test_no_motion_before_enable_and_mode_then_quick_stop_holds_until_resumed(make_rig) -> None:
    """The SDK alone, step by step: joint targets are ignored until the motors are enabled and CAN control in
    MOVE J is selected; after a quick stop they are ignored again, until a resume and a new mode selection."""
    rig = make_rig()
    left = piper_sdk.C_PiperInterface_V2(rig.channels[0], judge_flag=False, can_auto_init=False)
    left.CreateCanBus(rig.channels[0], bustype="virtual", judge_flag=False)
    left.ConnectPort()
    try:
        q0 = rig.sim.arm_joints()[0]
        move = [round(np.degrees(v) * 1000) for v in q0 + 0.1]
        left.JointCtrl(*move)
        time.sleep(0.2)
        assert np.abs(rig.sim.arm_joints()[0] - q0).max() < 1e-3  # not enabled, no mode: ignored

        assert _wait(lambda: left.EnablePiper())
        left.MotionCtrl_2(0x01, 0x01, 100, 0x00)
        left.JointCtrl(*move)
        assert _wait(lambda: np.abs(rig.sim.arm_joints()[0] - (q0 + 0.1)).max() < 2e-3)

        left.EmergencyStop(0x01)
        assert _wait(lambda: left.GetArmStatus().arm_status.arm_status == 0x01)
        held = rig.sim.arm_joints()[0]
        left.MotionCtrl_2(0x01, 0x01, 100, 0x00)
        left.JointCtrl(*[round(np.degrees(v) * 1000) for v in q0])
        time.sleep(0.2)
        assert np.abs(rig.sim.arm_joints()[0] - held).max() < 2e-3  # stopped: ignored

        left.EmergencyStop(0x02)
        assert _wait(lambda: left.GetArmStatus().arm_status.arm_status == 0x00)
        assert left.GetArmStatus().arm_status.ctrl_mode == 0x00  # back in standby
        left.MotionCtrl_2(0x01, 0x01, 100, 0x00)
        left.JointCtrl(*[round(np.degrees(v) * 1000) for v in q0])
        assert _wait(lambda: np.abs(rig.sim.arm_joints()[0] - q0).max() < 2e-3)
    finally:
        left.DisconnectPort()


def test_encoder_noise_reaches_the_sdk(make_rig, figures) -> None:
    rig = make_rig(encoder_noise=0.01)
    with _connect(rig) as driver:
        samples = []
        for _ in range(60):
            samples.append(driver.read().joint_pos - rig.sim.arm_joints())
            time.sleep(0.006)
        std = float(np.std(np.asarray(samples)))
        figures.add("piper_emulator.encoder_noise_std_rad(set 0.01)", round(std, 4))
        assert 0.005 < std < 0.02


def test_command_delay_postpones_the_motion(make_rig, figures) -> None:
    """With a 60 ms delay the arm cannot have moved before 60 ms have passed (a lower bound by construction)."""
    rig = make_rig(command_delay=0.06)
    with _connect(rig) as driver:
        before = rig.sim.arm_joints()
        target = before + 0.05
        sent = time.monotonic()
        driver.command(target, driver.read().gripper)
        assert _wait(lambda: np.abs(rig.sim.arm_joints() - before).max() > 1e-4)
        moved = time.monotonic() - sent
        figures.add("piper_emulator.delayed_motion_ms(delay 60)", round(moved * 1000, 1))
        assert moved >= 0.06


def test_dropped_feedback_frames(make_rig, figures) -> None:
    """With a drop probability of 0.5, about half of each feedback frame reaches a listener on the bus; the
    SDK still tracks the arm from the frames that arrive."""
    import can

    rig = make_rig(feedback_drop=0.5, rx_buffer=100_000)
    listener = can.Bus(interface="virtual", channel=rig.channels[0])
    try:
        with _connect(rig) as driver:
            while listener.recv(timeout=0.0) is not None:
                pass
            rounds = rig.emulator.feedback_rounds
            time.sleep(0.5)
            rounds = rig.emulator.feedback_rounds - rounds
            frames = []
            while (msg := listener.recv(timeout=0.0)) is not None:
                frames.append(msg.arbitration_id)
            share = frames.count(0x2A5) / rounds
            figures.add("piper_emulator.joint_frames_delivered_share(drop 0.5)", round(share, 3))
            assert rounds > 50 and 0.3 < share < 0.7
            target = driver.read().joint_pos + 0.05
            driver.command(target, driver.read().gripper)
            assert _wait(lambda: np.abs(driver.read().joint_pos - target).max() < 2e-3)
    finally:
        listener.shutdown()
