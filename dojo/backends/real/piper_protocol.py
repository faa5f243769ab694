"""The AgileX PiPER arm's CAN protocol (V2) from the arm's side: frame ids, units and byte layouts.

Written from the maker's protocol description (the field tables in piper-sdk's message docs), for the
emulator: it decodes the command frames the SDK sends and encodes the feedback frames the SDK reads. The
driver never uses this module (it goes through the unmodified `piper-sdk`), so a misreading here cannot cancel
out against the same misreading on the other side: the emulator tests would show it.

Every multi-byte field is big-endian; every frame has 8 data bytes and a standard (11-bit) id. Only the frames
the emulator answers are named here.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence

# Feedback (arm -> host).
STATUS = 0x2A1
JOINT_FEEDBACK = (0x2A5, 0x2A6, 0x2A7)  # joints 1-2, 3-4, 5-6
GRIPPER_FEEDBACK = 0x2A8
HIGH_SPEED = tuple(range(0x251, 0x257))  # one per joint driver: speed, current, position
LOW_SPEED = tuple(range(0x261, 0x267))   # one per joint driver: voltage, temperatures, status bits, current

# Commands (host -> arm).
MOTION_CTRL_1 = 0x150  # byte 0: 0x01 quick emergency stop, 0x02 resume
MOTION_CTRL_2 = 0x151  # control mode, move mode, speed percentage, MIT mode
JOINT_CTRL = (0x155, 0x156, 0x157)  # joint targets 1-2, 3-4, 5-6
GRIPPER_CTRL = 0x159
MOTOR_ENABLE = 0x471   # motor number (1-6, 7 = all), 0x01 disable / 0x02 enable

# Values of the fields the emulator reads or writes.
CTRL_STANDBY = 0x00
CTRL_CAN = 0x01
MOVE_J = 0x01
ARM_NORMAL = 0x00
ARM_EMERGENCY_STOP = 0x01
ESTOP_STOP = 0x01
ESTOP_RESUME = 0x02
ENABLE = 0x02
DISABLE = 0x01
ALL_MOTORS = 7
GRIPPER_ENABLE_BIT = 0x01   # in the gripper command's status code: 0x01/0x03 enable, 0x00/0x02 disable
DRIVER_ENABLED = 1 << 6     # in the low-speed feedback's and the gripper feedback's status byte

MILLIDEG_PER_RAD = 180_000.0 / math.pi  # joint angles travel in 0.001 degree
MICRON_PER_M = 1_000_000.0              # gripper stroke travels in 0.001 mm
MILLI = 1000.0                          # speeds (0.001 rad/s), currents (0.001 A), torques (0.001 N m)


def _i32(value: float) -> int:
    return max(-2**31, min(2**31 - 1, round(value)))


def _i16(value: float) -> int:
    return max(-2**15, min(2**15 - 1, round(value)))


def encode_status(ctrl_mode: int, arm_status: int, move_mode: int, reached: bool) -> bytes:
    """0x2A1: control mode, arm status, move mode, teach status (off), motion status (0 = target reached),
    trajectory point (0), error code (none)."""
    return struct.pack(">BBBBBBH", ctrl_mode, arm_status, move_mode, 0, 0 if reached else 1, 0, 0)


def encode_joints(q_rad: Sequence[float]) -> list[tuple[int, bytes]]:
    """0x2A5..0x2A7: six joint angles (radians) as (frame id, data), two int32 of 0.001 degree per frame."""
    millideg = [_i32(q * MILLIDEG_PER_RAD) for q in q_rad]
    return [(fid, struct.pack(">ii", millideg[2 * k], millideg[2 * k + 1])) for k, fid in enumerate(JOINT_FEEDBACK)]


def encode_gripper(width_m: float, effort_nm: float, enabled: bool) -> bytes:
    """0x2A8: stroke (int32, 0.001 mm), torque (int16, 0.001 N m), status byte, one reserved byte."""
    return struct.pack(">ihBx", _i32(width_m * MICRON_PER_M), _i16(effort_nm * MILLI),
                       DRIVER_ENABLED if enabled else 0)


def encode_high_speed(speed_rad_s: float, current_a: float, position_rad: float) -> bytes:
    """0x251..0x256: speed (int16, 0.001 rad/s), current (int16, 0.001 A), position (int32; the maker's table
    names no scale for it, the emulator sends 0.001 rad)."""
    return struct.pack(">hhi", _i16(speed_rad_s * MILLI), _i16(current_a * MILLI), _i32(position_rad * MILLI))


def encode_low_speed(enabled: bool, voltage_v: float = 24.0, temperature_c: float = 30.0) -> bytes:
    """0x261..0x266: bus voltage (uint16, 0.1 V), driver and motor temperature (int16 / int8, deg C), status
    byte (bit 6: driver enabled), bus current (uint16, 0.001 A)."""
    return struct.pack(">HhbBH", round(voltage_v * 10), round(temperature_c), round(temperature_c),
                       DRIVER_ENABLED if enabled else 0, 0)


def decode_joint_ctrl(frame_id: int, data: bytes) -> tuple[int, float, float]:
    """0x155..0x157 -> (index of the first of its two joints, both targets in radians)."""
    first = JOINT_CTRL.index(frame_id) * 2
    a, b = struct.unpack(">ii", bytes(data[:8]))
    return first, a / MILLIDEG_PER_RAD, b / MILLIDEG_PER_RAD


def decode_gripper_ctrl(data: bytes) -> tuple[float, float, bool]:
    """0x159 -> (stroke target in metres, torque limit in N m, enable)."""
    stroke, effort, code = struct.unpack(">ihB", bytes(data[:7]))
    return stroke / MICRON_PER_M, effort / MILLI, bool(code & GRIPPER_ENABLE_BIT)


def decode_motion_ctrl_2(data: bytes) -> tuple[int, int, int]:
    """0x151 -> (control mode, move mode, speed percentage 0..100)."""
    ctrl_mode, move_mode, speed = struct.unpack(">BBB", bytes(data[:3]))
    return ctrl_mode, move_mode, min(speed, 100)


def decode_motor_enable(data: bytes) -> tuple[int, bool]:
    """0x471 -> (motor number, 1-6 or 7 for all; True to enable)."""
    motor, flag = struct.unpack(">BB", bytes(data[:2]))
    return motor, flag == ENABLE
