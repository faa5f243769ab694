"""The PiPER arms' controllers, emulated on a CAN bus: the unmodified `piper-sdk` drives the emulated world.

One bus per arm, as on the real robot (one USB-CAN adapter per arm). The emulator answers like the arm's main
controller: it accepts motor enable/disable (0x471), the control and move mode with the speed percentage
(0x151), joint targets (0x155-0x157), gripper targets (0x159) and the quick emergency stop / resume (0x150),
and publishes at `feedback_hz` the arm status (0x2A1), joint angles (0x2A5-0x2A7), gripper (0x2A8) and the
drivers' high-speed feedback (0x251-0x256, joint speeds), with the low-speed feedback (0x261-0x266, which
carries the motors' enable bits) at a tenth of that rate.

Like the firmware, the emulator moves an arm only when all six motors are enabled, the control mode is CAN
and the move mode is MOVE J (the sequence `PiperDriver.connect` performs), and not after a quick stop until it
is resumed. A resume (0x150 byte 0 = 0x02) returns to standby, so the host has to select the mode again; the
real arm also drops its motors' power at that point, which the emulator does not imitate.

The bus is python-can's: `virtual` by default (in-process, channels by name), or any other interface, e.g.
`socketcan` on a CAN adapter wired to the robot computer's (a same-host `vcan` does not carry piper-sdk's
commands: see piper_driver). A virtual channel has no kernel socket buffer, so a bus that nobody reads
(the SDK opens a separate send-only bus on Linux) would grow without limit; the emulator keeps every other
queue on its channel at most `rx_buffer` frames long, dropping the oldest, as a full socket buffer would.

Imperfections are parameters (`emulator.EmulatorParams`): encoder noise on the joint feedback, a delay before a
command takes effect, and a probability that any feedback frame is lost. Every command frame's arrival is
logged on the emulator's clock (`received`), which is how latencies are measured, with the time the bus stamped
it (when the SDK put it on the bus, for python-can's virtual bus; its reception, for a kernel bus), moved to the
same clock: the two differ by how late the emulator's thread, standing in for the arm's own controller, got to
it.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

import can
import numpy as np
from can.interfaces.virtual import VirtualBus

from dojo.backends.real import piper_protocol as P
from dojo.backends.real.emulator import EmulatorParams
from dojo.backends.real.realtime_sim import RealTimeSim


@dataclass(frozen=True)
class ReceivedFrame:
    """A command frame as the emulator got it: arrival time (emulator clock), arm index, frame id, and the bus's
    time stamp of it on the emulator clock."""

    time: float
    arm: int
    frame_id: int
    on_bus: float


LOW_SPEED_DIVIDER = 10
"""The low-speed driver feedback goes out once every this many periodic feedbacks."""


class _ArmController:
    """One PiPER main controller: its mode state, its pending commands and its bus."""

    def __init__(self, sim: RealTimeSim, arm: int, bus: can.BusABC, params: EmulatorParams,
                 rng: np.random.Generator) -> None:
        self.sim, self.arm, self.bus, self.params, self.rng = sim, arm, bus, params, rng
        self.enabled = np.zeros(6, dtype=bool)
        self.gripper_enabled = False
        self.ctrl_mode, self.move_mode, self.speed = P.CTRL_STANDBY, P.MOVE_J, 1.0
        self.stopped = False
        self.joint_cmd = sim.reading(arm).joint_pos
        self.pending: collections.deque[tuple[float, int, bytes]] = collections.deque()

    @property
    def accepts_motion(self) -> bool:
        return bool(self.enabled.all()) and self.ctrl_mode == P.CTRL_CAN and self.move_mode == P.MOVE_J \
            and not self.stopped

    def receive(self, now: float) -> list[ReceivedFrame]:
        """Take the frames that arrived, apply those whose delay has passed; return the arrivals."""
        arrived = []
        wall_to_clock = self.sim.clock() - time.time()
        while (msg := self.bus.recv(timeout=0.0)) is not None:
            arrived.append(ReceivedFrame(now, self.arm, msg.arbitration_id, msg.timestamp + wall_to_clock))
            self.pending.append((now + self.params.command_delay, msg.arbitration_id, bytes(msg.data)))
        while self.pending and self.pending[0][0] <= now:
            _, frame_id, data = self.pending.popleft()
            self.apply(frame_id, data)
        return arrived

    def apply(self, frame_id: int, data: bytes) -> None:
        """One command frame's effect, as the arm's firmware would have it."""
        if frame_id == P.MOTOR_ENABLE:
            motor, on = P.decode_motor_enable(data)
            if motor == P.ALL_MOTORS:
                self.enabled[:] = on
            elif 1 <= motor <= 6:
                self.enabled[motor - 1] = on
        elif frame_id == P.MOTION_CTRL_2:
            self.ctrl_mode, self.move_mode, percent = P.decode_motion_ctrl_2(data)
            self.speed = max(percent, 1) / 100.0
        elif frame_id == P.MOTION_CTRL_1:
            if data[0] == P.ESTOP_STOP:
                self.stopped = True
                self.sim.hold_arm(self.arm)
            elif data[0] == P.ESTOP_RESUME:
                self.stopped, self.ctrl_mode = False, P.CTRL_STANDBY
        elif frame_id in P.JOINT_CTRL:
            first, a, b = P.decode_joint_ctrl(frame_id, data)
            self.joint_cmd[first:first + 2] = a, b
            if self.accepts_motion:
                self.sim.set_joint_target(self.arm, self.joint_cmd, self.speed)
        elif frame_id == P.GRIPPER_CTRL:
            width, _, self.gripper_enabled = P.decode_gripper_ctrl(data)
            if self.gripper_enabled and not self.stopped:
                self.sim.set_gripper_target(self.arm, width)

    def publish(self, low_speed: bool) -> None:
        """One round of periodic feedback (each frame lost with probability `feedback_drop`)."""
        now = self.sim.reading(self.arm)
        q = now.joint_pos + self.rng.normal(0.0, self.params.encoder_noise, 6) if self.params.encoder_noise \
            else now.joint_pos
        status = P.ARM_EMERGENCY_STOP if self.stopped else P.ARM_NORMAL
        frames = [(P.STATUS, P.encode_status(self.ctrl_mode, status, self.move_mode, now.at_target)),
                  *P.encode_joints(q),
                  (P.GRIPPER_FEEDBACK, P.encode_gripper(now.width, now.gripper_force, self.gripper_enabled))]
        frames += [(fid, P.encode_high_speed(v, 0.0, p)) for fid, v, p in zip(P.HIGH_SPEED, now.joint_vel, q)]
        if low_speed:
            frames += [(fid, P.encode_low_speed(bool(on))) for fid, on in zip(P.LOW_SPEED, self.enabled)]
        for frame_id, data in frames:
            if self.params.feedback_drop and self.rng.random() < self.params.feedback_drop:
                continue
            self.bus.send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=False))
        self._trim_readers()

    def _trim_readers(self) -> None:
        """Keep the other queues of a virtual channel at most `rx_buffer` frames long (oldest dropped)."""
        if not isinstance(self.bus, VirtualBus):
            return  # a kernel bus (socketcan): the kernel bounds its own buffers
        for queue in list(self.bus.channel):
            while queue is not self.bus.queue and queue.qsize() > self.params.rx_buffer:
                queue.get_nowait()


class PiperCanEmulator:
    """The controllers of a bimanual PiPER on `channels` (left arm's bus, right arm's bus), attached to `sim`."""

    def __init__(self, sim: RealTimeSim, channels: Sequence[str], interface: str = "virtual",
                 params: EmulatorParams = EmulatorParams()) -> None:
        if len(channels) != 2:
            raise ValueError(f"a bimanual PiPER has one CAN bus per arm; got channels {list(channels)}")
        self.params = params
        self.received: collections.deque[ReceivedFrame] = collections.deque(maxlen=100_000)
        rng = np.random.default_rng(params.seed)
        self._arms = [_ArmController(sim, arm, can.Bus(interface=interface, channel=channel), params, rng)
                      for arm, channel in enumerate(channels)]
        self._period = 1.0 / params.feedback_hz
        self._next_feedback = 0.0
        self.feedback_rounds = 0
        """Periodic feedback rounds published so far (each sends every feedback frame once, less drops)."""
        self._lock = threading.Lock()
        sim.add_listener(self)

    def before_step(self, now: float) -> None:
        for arm in self._arms:
            arrived = arm.receive(now)
            if arrived:
                with self._lock:
                    self.received.extend(arrived)

    def after_step(self, now: float) -> None:
        if now < self._next_feedback:
            return
        self._next_feedback = max(self._next_feedback + self._period, now)
        low_speed = self.feedback_rounds % LOW_SPEED_DIVIDER == 0
        self.feedback_rounds += 1
        for arm in self._arms:
            arm.publish(low_speed)

    def frames_since(self, t: float) -> list[ReceivedFrame]:
        """Command frames that arrived at or after emulator time `t`, oldest first."""
        with self._lock:
            return [f for f in self.received if f.time >= t]

    def close(self) -> None:
        """Shut the buses (stop the `RealTimeSim` first: its thread calls this emulator)."""
        for arm in self._arms:
            arm.bus.shutdown()
