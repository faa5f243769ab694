"""The safety layer: each kind of bad command is clipped or refused, and counted; the watchdog holds; the e-stop
holds at once and returns slowly to the reset pose, and reaches the emulated arms fast (a measured figure).

Most checks run against a stand-in driver that records what it is sent and teleports to it, with the PiPER's
real configuration; where a check must be isolated from the others (a target below the table is also a huge
jump from home), the other limits are loosened. The e-stop test drives the emulated PiPER through piper-sdk.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from dojo.backends.real.driver import Driver, RobotState
from dojo.backends.real.safety import ESTOP, HOLDING, RETURNING, RUNNING, STOPPED, SafetyLayer
from dojo.backends.real.workspace import RobotGeometry
from safety_rig import CONTROL_HZ, commanding_away, latency_summary, rig_safety

BELOW_TABLE = [0.0, 2.0, -0.9, 0.0, 0.4, 0.0]      # shoulder pitched down: the hand goes through the table
OUT_SIDEWAYS = [1.57, 1.57, -1.0, 0.0, 0.0, 0.0]   # left arm stretched out to the left, beyond x = -0.75


class StandIn(Driver):
    """Records every command and is instantly where it was sent."""

    def __init__(self, home_q: np.ndarray, home_grip: np.ndarray) -> None:
        self._home = (home_q.copy(), home_grip.copy())
        self.q, self.grip = home_q.copy(), home_grip.copy()
        self.sent: list[tuple[np.ndarray, np.ndarray, float]] = []

    @property
    def home_pose(self) -> tuple[np.ndarray, np.ndarray]:
        return self._home[0].copy(), self._home[1].copy()

    def connect(self) -> None:
        pass

    def read(self) -> RobotState:
        return RobotState(self.q.copy(), np.zeros_like(self.q), self.grip.copy(), 0.0)

    def command(self, joint_pos: np.ndarray, gripper: np.ndarray, speed: float = 1.0) -> None:
        self.sent.append((np.array(joint_pos), np.array(gripper), speed))
        self.q, self.grip = np.array(joint_pos), np.array(gripper)

    def estop(self) -> None:
        raise AssertionError("the safety layer's e-stop must not use the hardware stop")


@pytest.fixture
def layer(piper_world):
    """A SafetyLayer over a stand-in at the PiPER's home, with the real configuration, and a settable clock."""
    model, robot, config = piper_world
    ctrl = np.asarray(robot["home_ctrl"]).reshape(2, -1)
    driver = StandIn(ctrl[:, :-1], ctrl[:, -1] / robot["gripper_max_width"])
    now = [0.0]
    safety = SafetyLayer(driver, RobotGeometry(model, robot), config, CONTROL_HZ, clock=lambda: now[0])
    safety.now = now
    return safety


def _loosen(safety: SafetyLayer) -> None:
    """No jump, velocity or acceleration limit: the placement checks alone decide."""
    safety.config = dataclasses.replace(safety.config, max_jump=100.0, joint_velocity=np.full(6, 1e6),
                                        joint_acceleration=np.full(6, 1e9))


def test_non_finite_commands_are_refused_and_nothing_is_sent(layer) -> None:
    q, grip = layer.driver.home_pose
    bad_q = q.copy()
    bad_q[0, 2] = np.nan
    assert layer.command(bad_q, grip).refused == "refused_nonfinite"
    assert layer.command(q, np.array([np.inf, 0.5])).refused == "refused_nonfinite"
    assert layer.driver.sent == [] and layer.counters["refused_nonfinite"] == 2


def test_a_huge_jump_is_refused(layer) -> None:
    q, grip = layer.driver.home_pose
    far = q.copy()
    far[1, 0] += 1.0  # max_jump is 0.6 rad
    assert layer.command(far, grip).refused == "refused_jump"
    assert layer.driver.sent == [] and layer.counters["refused_jump"] == 1


def test_joint_ranges_and_grippers_are_clipped(layer) -> None:
    layer.driver.q[0, 3] = 1.81  # joint 4's range ends at 1.832
    layer.new_trial()
    target = layer.driver.q.copy()
    target[0, 3] = 1.9
    verdict = layer.command(target, np.array([1.3, -0.2]))
    assert verdict.sent and set(verdict.clipped) == {"clipped_joint_limit", "clipped_gripper"}
    sent_q, sent_grip, _ = layer.driver.sent[-1]
    assert sent_q[0, 3] == pytest.approx(1.832) and list(sent_grip) == [1.0, 0.0]
    assert layer.counters["clipped_joint_limit"] == 1 and layer.counters["clipped_gripper"] == 1


def test_velocity_and_acceleration_are_clipped_without_overshoot(layer) -> None:
    """From rest, a 0.3 rad step on joint 1: the first command may speed up by 15 rad/s^2 * 40 ms only, later
    ones by as much again, never beyond 2.5 rad/s, and the arm ends exactly at the target."""
    q, grip = layer.driver.home_pose
    target = q.copy()
    target[0, 0] += 0.3
    steps = []
    for _ in range(20):
        verdict = layer.command(target, grip)
        assert verdict.sent
        steps.append(layer.driver.sent[-1][0][0, 0] - q[0, 0])
    dt = 1.0 / CONTROL_HZ
    assert steps[0] == pytest.approx(15 * dt * dt)
    assert steps[1] == pytest.approx(3 * 15 * dt * dt)
    assert np.all(np.diff(steps) <= 2.5 * dt + 1e-12) and max(steps) == pytest.approx(0.3) and steps[-1] == 0.3
    assert layer.counters["clipped_velocity"] >= 1 and layer.counters["clipped_acceleration"] >= 2


def test_a_target_below_the_table_is_refused(layer) -> None:
    _loosen(layer)
    q, grip = layer.driver.home_pose
    q[0] = BELOW_TABLE
    assert layer.command(q, grip).refused == "refused_table"
    assert layer.driver.sent == [] and layer.counters["refused_table"] == 1


def test_a_target_outside_the_workspace_is_refused(layer) -> None:
    _loosen(layer)
    q, grip = layer.driver.home_pose
    q[0] = OUT_SIDEWAYS
    assert layer.command(q, grip).refused == "refused_workspace"
    assert layer.driver.sent == [] and layer.counters["refused_workspace"] == 1


@pytest.mark.parametrize(("turn", "refused"), [(0.6, None), (0.9, "refused_arm_collision")])
def test_a_target_crossing_the_arms_is_refused(layer, turn: float, refused: str | None) -> None:
    """Both base joints turned towards the other arm: 0.6 rad leaves 8 cm between the arms, 0.9 rad crosses them
    (each arm alone is inside the workspace and above the table)."""
    _loosen(layer)
    q, grip = layer.driver.home_pose
    q[0, 0], q[1, 0] = -turn, turn
    verdict = layer.command(q, grip)
    assert verdict.refused == refused and verdict.sent == (refused is None)
    assert layer.counters["refused_arm_collision"] == (refused is not None)


def test_the_watchdog_holds_when_commands_stop(layer) -> None:
    q, grip = layer.driver.home_pose
    assert layer.command(q, grip).sent
    layer.tick(0.2)  # 200 ms: within the 250 ms watchdog
    assert layer.state == RUNNING and len(layer.driver.sent) == 1
    layer.tick(0.3)
    assert layer.state == HOLDING and layer.counters["watchdog_holds"] == 1
    held_q, held_grip, _ = layer.driver.sent[-1]
    assert np.array_equal(held_q, layer.driver.q) and np.array_equal(held_grip, grip)
    layer.tick(1.0)
    assert layer.counters["watchdog_holds"] == 1  # one hold, not one per tick
    layer.now[0] = 1.0
    assert layer.command(q, grip).sent and layer.state == RUNNING


def test_estop_holds_refuses_returns_slowly_and_waits_for_the_operator(layer) -> None:
    q, grip = layer.driver.home_pose
    moved = q.copy()
    moved[0, 0] += 0.02
    assert layer.command(moved, grip).sent
    layer.now[0] = 1.0
    assert layer.estop() == 1.0 and layer.state == ESTOP
    assert np.array_equal(layer.driver.sent[-1][0], moved)  # held where it was
    assert layer.command(q, grip).refused == "refused_estop"
    layer.tick(1.0 + layer.config.estop_hold_s / 2)
    assert layer.state == ESTOP
    layer.tick(1.0 + layer.config.estop_hold_s)
    home_q, _, speed = layer.driver.sent[-1]
    assert layer.state == RETURNING and np.array_equal(home_q, q) and speed == layer.config.return_speed
    layer.tick(2.0)  # the stand-in is already home
    assert layer.state == STOPPED
    assert layer.command(q, grip).refused == "refused_estop" and layer.counters["refused_estop"] == 2
    layer.release()
    assert layer.command(q, grip).sent


def test_the_estop_does_not_wait_for_a_command_being_checked(layer) -> None:
    """The policy's thread is inside a command's checks (holding the check lock) when the e-stop comes: the hold
    goes out at once, and the command, when its checks end, is refused instead of sent after the hold."""
    q, grip = layer.driver.home_pose
    inside, go_on = threading.Event(), threading.Event()
    place = layer._placement

    def slow_placement(*args):
        inside.set()
        go_on.wait()
        return place(*args)

    layer._placement = slow_placement
    verdicts = []
    policy = threading.Thread(target=lambda: verdicts.append(layer.command(q, grip)), daemon=True)
    policy.start()
    assert inside.wait(10)
    estop = threading.Thread(target=layer.estop, daemon=True)
    estop.start()
    estop.join(10)
    assert not estop.is_alive(), "the e-stop waited for the command's checks"
    assert len(layer.driver.sent) == 2 and layer.state == ESTOP  # the hold, sent twice
    go_on.set()
    policy.join(10)
    assert verdicts[0].refused == "refused_estop" and len(layer.driver.sent) == 2


def test_a_command_already_being_sent_is_followed_by_the_estops_hold(layer) -> None:
    """The policy's command is on its way to the driver when the e-stop comes: the e-stop's first hold does not
    wait for it, and its second hold comes after it, so the arms end held, not at the policy's target."""
    q, grip = layer.driver.home_pose
    target = q.copy()
    target[0, 0] += 0.01
    sending, go_on = threading.Event(), threading.Event()
    send = layer.driver.command

    def slow_send(joint_pos, gripper, speed=1.0):
        if np.array_equal(joint_pos, target):
            sending.set()
            go_on.wait()
        send(joint_pos, gripper, speed)

    layer.driver.command = slow_send
    policy = threading.Thread(target=layer.command, args=(target, grip), daemon=True)
    policy.start()
    assert sending.wait(10)
    estop = threading.Thread(target=layer.estop, daemon=True)
    estop.start()
    while len(layer.driver.sent) < 1:  # the first hold, sent while the policy's command is still on its way
        time.sleep(0.001)
    go_on.set()
    policy.join(10)
    estop.join(10)
    # the first hold (at home, where the arm was), the policy's command, the second hold (the stand-in is
    # instantly at its target: held there)
    assert [np.array_equal(sent_q, target) for sent_q, _, _ in layer.driver.sent] == [False, True, True]
    assert np.array_equal(layer.driver.sent[0][0], q)
    assert layer.state == ESTOP


@pytest.mark.slow
def test_estop_latency_over_many_presses_with_the_machine_loaded(make_rig, figures) -> None:
    """The figure the e-stop's bar is about, under load: busy loops in 2 x cores other processes, a policy
    commanding both arms at 25 Hz; PRESSES e-stops, each released after a moment. Per press, from the call:
    the first hold frame on the arms' bus (its bus time stamp), and seen by the emulated arm controller (whose
    thread shares the loaded process and CPUs, as a real arm's controller would not)."""
    pytest.importorskip("piper_sdk")
    from dojo.backends.real.piper_driver import PiperDriver

    presses = 60
    rig = make_rig()
    load = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2 * (os.cpu_count() or 1))]
    on_bus, seen = [], []
    try:
        with PiperDriver(rig.robot, rig.channels, interface="virtual") as driver:
            driver.connect()
            safety = rig_safety(rig, driver)
            rng = np.random.default_rng(0)
            try:
                with commanding_away(safety):
                    for _ in range(presses):
                        time.sleep(rng.uniform(0.1, 0.25))
                        pressed = rig.sim.clock()
                        safety.estop()
                        while not (frames := rig.emulator.frames_since(pressed)):
                            time.sleep(0.0005)
                        on_bus.append(min(f.on_bus for f in rig.emulator.frames_since(pressed)) - pressed)
                        seen.append(frames[0].time - pressed)
                        time.sleep(0.05)
                        assert safety.state == ESTOP
                        safety.release()
            finally:
                safety.close()
    finally:
        for process in load:
            process.kill()
            process.wait()

    figures.add(f"safety.estop_under_load_ms({2 * (os.cpu_count() or 1)} busy processes; call -> hold on the bus)",
                latency_summary(on_bus))
    figures.add("safety.estop_under_load_ms(call -> seen by the emulated arm controller)", latency_summary(seen))
    assert len(on_bus) == presses


def test_a_new_trial_zeroes_the_counters(layer) -> None:
    q, grip = layer.driver.home_pose
    layer.command(q * np.nan, grip)
    layer.new_trial()
    assert not any(layer.counters.values())


def test_estop_reaches_the_emulated_arms_and_returns_them_slowly(make_rig, figures) -> None:
    """A policy thread commands both arms at 25 Hz; the operator's e-stop comes from another thread. Measured on
    the emulator's clock: trigger to the first hold frame arriving on the arms' buses; then the return."""
    pytest.importorskip("piper_sdk")
    from dojo.backends.real.piper_driver import PiperDriver

    rig = make_rig()
    with PiperDriver(rig.robot, rig.channels, interface="virtual") as driver:
        driver.connect()
        safety = rig_safety(rig, driver)
        try:
            with commanding_away(safety) as home_q:
                time.sleep(0.4)
                trigger = safety.estop()
                arrivals = rig.emulator.frames_since(trigger)
                while not arrivals:
                    time.sleep(0.001)
                    arrivals = rig.emulator.frames_since(trigger)
                latency_ms = (arrivals[0].time - trigger) * 1000.0
                stopped_at = rig.sim.arm_joints()
                speeds = []
                deadline = time.monotonic() + 20.0
                while safety.state != STOPPED and time.monotonic() < deadline:
                    if safety.state == RETURNING and rig.sim.clock() - trigger > rig.config.estop_hold_s + 0.2:
                        speeds.append(np.abs(driver.read().joint_vel).max())
                    time.sleep(0.01)
                returned_s = rig.sim.clock() - trigger
        finally:
            safety.close()
        assert safety.state == STOPPED
        assert np.abs(rig.sim.arm_joints() - home_q).max() < 0.02
        assert np.abs(stopped_at - home_q).max() > 0.05  # it had moved away, and came back
        assert safety.counters["refused_estop"] > 0
        bound = float(rig.config.return_speed * rig.config.joint_velocity.max())
        figures.add("safety.estop_to_driver_ms", round(latency_ms, 2))
        figures.add("safety.estop_return_s", round(returned_s, 2))
        figures.add("safety.return_peak_joint_speed_rad_s", {"measured": round(float(max(speeds)), 3),
                                                             "bound": round(bound, 3)})
        assert max(speeds) < 1.5 * bound
