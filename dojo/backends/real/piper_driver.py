"""The AgileX PiPER / PiPER X driver, through the maker's unmodified `piper-sdk` (one CAN bus per arm).

The SDK is used only through its public interface (`C_PiperInterface_V2`). It opens SocketCAN by default; its
documented `CreateCanBus(can_name, bustype=...)` chooses another python-can interface, which is how the same
driver talks to the emulator (`interface="virtual"`, in-process). A `vcan` port on the same machine does not
work with piper-sdk 0.6.2: it opens its sockets without local loopback, so no other socket on the host sees its
commands (an emulator on a second machine, wired to this one's CAN adapter, does). On hardware (`socketcan`) the
SDK first checks that the port exists, is up and runs at 1 Mbit/s.

Start-up is the maker's sequence: connect, enable all motors until the drivers report enabled, select CAN
control in MOVE J with a speed percentage (the gripper is enabled by its first command). Each command
re-selects the mode before the joint targets, as the maker's joint-control example does, so an arm that fell
back to standby follows again.

Units on the wire: joint angles in 0.001 degree, gripper stroke in 0.001 mm, speeds in 0.001 rad/s.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from dojo.backends.real.driver import Driver, RobotState, home_of

MILLIDEG_PER_RAD = 180_000.0 / math.pi
MICRON_PER_M = 1_000_000.0
CAN_CONTROL, MOVE_J, POSITION_VELOCITY = 0x01, 0x01, 0x00
GRIPPER_ENABLE = 0x01
QUICK_STOP = 0x01
GRIPPER_EFFORT = 1000
"""Gripper torque limit in 0.001 N m (1 N m, the maker's examples' value)."""


class PiperDriver(Driver):
    """Both arms of a bimanual PiPER (or PiPER X), one `C_PiperInterface_V2` per CAN bus."""

    def __init__(self, robot: Mapping[str, Any], channels: Sequence[str] = ("can_left", "can_right"),
                 interface: str = "socketcan", connect_timeout: float = 5.0) -> None:
        """`robot`: the compiler's robot handles (home pose, gripper width); `channels`: the left and the right
        arm's CAN bus; `interface`: python-can interface (`socketcan` on hardware, `virtual` for the emulator)."""
        if len(channels) != 2:
            raise ValueError(f"a bimanual PiPER has one CAN bus per arm; got channels {list(channels)}")
        self.channels, self.interface, self.connect_timeout = tuple(channels), interface, connect_timeout
        self.robot = dict(robot)
        self._home, self.max_width = home_of(robot)
        self._arms: list[Any] = []

    @property
    def home_pose(self) -> tuple[np.ndarray, np.ndarray]:
        return self._home[0].copy(), self._home[1].copy()

    def connect(self, enable: bool = True) -> None:
        """As `Driver.connect`; with `enable=False` only listen until the arms report (a second connection to
        arms another process drives, as the console's e-stop process is: it changes nothing until it holds)."""
        from piper_sdk import C_PiperInterface_V2

        started, deadline = time.time(), time.monotonic() + self.connect_timeout
        for channel in self.channels:
            arm = C_PiperInterface_V2(channel, judge_flag=False, can_auto_init=False)
            with warnings.catch_warnings():
                # The SDK passes python-can's deprecated `bustype` keyword; nothing of ours to fix.
                warnings.filterwarnings("ignore", message=".*'bustype' argument is deprecated",
                                        category=DeprecationWarning)
                arm.CreateCanBus(channel, bustype=self.interface, judge_flag=self.interface == "socketcan")
            arm.ConnectPort()
            self._arms.append(arm)
        for arm, channel in zip(self._arms, self.channels if enable else ()):
            while not arm.EnablePiper():
                if time.monotonic() > deadline:
                    raise TimeoutError(f"PiPER on {channel}: motors not enabled after {self.connect_timeout} s")
                time.sleep(0.01)
            arm.MotionCtrl_2(CAN_CONTROL, MOVE_J, 100, POSITION_VELOCITY)
        # CAN frames carry wall-clock receive times: wait for joint feedback newer than this connection.
        while any(arm.GetArmJointMsgs().time_stamp < started for arm in self._arms):
            if time.monotonic() > deadline:
                raise TimeoutError(f"PiPER on {self.channels}: no joint feedback after {self.connect_timeout} s")
            time.sleep(0.005)

    def read(self) -> RobotState:
        pos, vel, grip, stamps = [], [], [], []
        for arm in self._arms:
            joints = arm.GetArmJointMsgs()
            js = joints.joint_state
            pos.append([js.joint_1, js.joint_2, js.joint_3, js.joint_4, js.joint_5, js.joint_6])
            high = arm.GetArmHighSpdInfoMsgs()
            vel.append([getattr(high, f"motor_{k}").motor_speed for k in range(1, 7)])
            gripper = arm.GetArmGripperMsgs()
            grip.append(gripper.gripper_state.grippers_angle)
            stamps += [joints.time_stamp, gripper.time_stamp]
        return RobotState(
            joint_pos=np.asarray(pos, dtype=float) / MILLIDEG_PER_RAD,
            joint_vel=np.asarray(vel, dtype=float) / 1000.0,
            gripper=np.clip(np.asarray(grip, dtype=float) / MICRON_PER_M / self.max_width, 0.0, 1.0),
            stamp=float(max(stamps)),
        )

    def command(self, joint_pos: np.ndarray, gripper: np.ndarray, speed: float = 1.0) -> None:
        percent = int(np.clip(round(speed * 100), 1, 100))
        millideg = np.rint(np.asarray(joint_pos, dtype=float) * MILLIDEG_PER_RAD).astype(int)
        microns = np.rint(np.clip(gripper, 0.0, 1.0) * self.max_width * MICRON_PER_M).astype(int)
        for arm, q, width in zip(self._arms, millideg, microns):
            arm.MotionCtrl_2(CAN_CONTROL, MOVE_J, percent, POSITION_VELOCITY)
            arm.JointCtrl(*(int(v) for v in q))
            arm.GripperCtrl(int(width), GRIPPER_EFFORT, GRIPPER_ENABLE, 0)

    def estop(self) -> None:
        for arm in self._arms:
            arm.EmergencyStop(QUICK_STOP)

    def close(self) -> None:
        for arm in self._arms:
            arm.DisconnectPort()
        self._arms = []
