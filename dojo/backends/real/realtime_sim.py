"""The emulator's physical robot: a MuJoCo world stepped against the wall clock in its own thread.

The world is the compiler's own (a robot-only world from `build_robot_world`, or a plan's scene), so the arms
the emulator moves are exactly the arms the simulator scores. Each arm has a joint controller like the makers'
firmware: a target, and a setpoint that moves towards it at no more than the arm's maximum joint speeds times a
speed fraction (the PiPER's "move speed percentage"); the position servos of the model track the setpoint.
Grippers take a width target directly.

Protocol emulators (the PiPER's CAN controller, ...) attach as listeners: every tick, `before_step(now)` runs
before physics catches up with the clock (read commands, apply those that are due) and `after_step(now)` after
it (publish feedback). Everything runs in the one thread, so a listener may call the controller methods below
without locking; other threads (the backend's renderer, tests) read through the lock-taking methods.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import mujoco
import numpy as np

from dojo.backends.mujoco.kinematics import RobotIndex

TICK_S = 0.001
"""Period of the emulator loop: commands wait at most this long before the controller sees them."""
MAX_CATCHUP_S = 0.05
"""Physics falls behind the clock by at most this much (a stalled process); the rest of the gap is skipped and
counted in `lag_events`, as a real arm does not replay time it was not given."""


class Listener(Protocol):
    """A protocol emulator attached to the world (see the module docstring)."""

    def before_step(self, now: float) -> None: ...

    def after_step(self, now: float) -> None: ...


@dataclass(frozen=True)
class ArmReading:
    """One arm as its encoders see it (no noise: the protocol emulator adds its own)."""

    joint_pos: np.ndarray
    joint_vel: np.ndarray
    width: float
    gripper_force: float
    at_target: bool


class RealTimeSim:
    """A MuJoCo world with two joint-controlled arms, stepped in real time once `start()`ed."""

    def __init__(self, model: mujoco.MjModel, robot: Mapping[str, Any], max_joint_speed: Sequence[float],
                 qpos: Sequence[float] | None = None) -> None:
        """`robot`: the compiler's robot handles (a plan's `robot`, or `asdict(RobotHandles)`); `max_joint_speed`
        [J] rad/s at speed fraction 1; `qpos`: the initial state (the robot's home when None)."""
        self.max_joint_speed = np.asarray(max_joint_speed, dtype=float)
        self.lock = threading.Lock()
        self.lag_events = 0
        self._listeners: list[Listener] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.load(model, robot, qpos)

    @staticmethod
    def clock() -> float:
        """The emulator's clock (monotonic seconds): every emulator timestamp is on it."""
        return time.monotonic()

    def load(self, model: mujoco.MjModel, robot: Mapping[str, Any], qpos: Sequence[float] | None = None) -> None:
        """Replace the world (a new plan's scene) without stopping the loop or the protocol emulators; the
        controllers' targets become the new initial pose."""
        data = mujoco.MjData(model)
        index = RobotIndex.build(model, robot)
        if qpos is None:
            for name, value in robot["home_qpos"].items():
                data.qpos[model.joint(name).qposadr[0]] = value
            data.ctrl[index.actuators] = robot["home_ctrl"]
        else:
            data.qpos[:] = qpos
        mujoco.mj_forward(model, data)
        with self.lock:
            self.model, self.data, self.index = model, data, index
            self._gripper_acts = index.actuators.reshape(2, -1)[:, -1]
            self._joint_acts = index.actuators.reshape(2, -1)[:, :-1]
            self._target = index.arm_q(data).copy()
            self._setpoint = self._target.copy()
            self._speed = np.ones(2)
            self._width = data.ten_length[index.tendons].copy()

    def add_listener(self, listener: Listener) -> None:
        self._listeners.append(listener)

    # ---- the controllers (call from a listener, i.e. the loop's thread, or under `lock`) ----

    def set_joint_target(self, arm: int, joint_pos: np.ndarray, speed: float) -> None:
        """Move arm `arm` to `joint_pos` (clipped to the joint ranges) at `speed` (0..1] of the maximum."""
        lo, hi = self.index.limits.joint_lo[arm], self.index.limits.joint_hi[arm]
        self._target[arm] = np.clip(joint_pos, lo, hi)
        self._speed[arm] = float(np.clip(speed, 0.01, 1.0))

    def set_gripper_target(self, arm: int, width: float) -> None:
        self._width[arm] = float(np.clip(width, 0.0, self.index.limits.max_width))

    def hold_arm(self, arm: int) -> None:
        """Stop arm `arm` where it is now (target and setpoint at the measured joints)."""
        q = self.index.arm_q(self.data)[arm]
        self._target[arm] = q
        self._setpoint[arm] = q

    def reading(self, arm: int) -> ArmReading:
        """Arm `arm` now (called from a listener: no lock)."""
        d, ix = self.data, self.index
        return ArmReading(
            joint_pos=ix.arm_q(d)[arm].copy(),
            joint_vel=d.qvel[ix.dof_adr[arm]].copy(),
            width=float(d.ten_length[ix.tendons[arm]]),
            gripper_force=float(d.actuator_force[self._gripper_acts[arm]]),
            at_target=bool(np.allclose(self._setpoint[arm], self._target[arm])),
        )

    # ---- for other threads ----

    def snapshot(self) -> tuple[mujoco.MjModel, np.ndarray]:
        """The model and a copy of its qpos now, for rendering or checks outside the loop."""
        with self.lock:
            return self.model, self.data.qpos.copy()

    def arm_joints(self) -> np.ndarray:
        """True joint positions [2, J] now (tests compare the driver's view with them)."""
        with self.lock:
            return self.index.arm_q(self.data).copy()

    # ---- the loop ----

    def start(self) -> None:
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="dojo-emulator", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            self._thread = None

    def _run(self) -> None:
        sim_time = self.clock()
        while not self._stop.is_set():
            now = self.clock()
            for listener in self._listeners:
                listener.before_step(now)
            with self.lock:
                dt = self.model.opt.timestep
                if now - sim_time > MAX_CATCHUP_S:
                    self.lag_events += 1
                    sim_time = now - MAX_CATCHUP_S
                steps = int((now - sim_time) / dt)
                if steps:
                    self._advance(steps, dt)
                    sim_time += steps * dt
            for listener in self._listeners:
                listener.after_step(now)
            self._stop.wait(max(0.0, TICK_S - (self.clock() - now)))

    def _advance(self, steps: int, dt: float) -> None:
        """Move the setpoints towards the targets (rate-limited) and step the physics `steps` times."""
        reach = self.max_joint_speed[None, :] * self._speed[:, None] * steps * dt
        self._setpoint += np.clip(self._target - self._setpoint, -reach, reach)
        self.data.ctrl[self._joint_acts] = self._setpoint
        self.data.ctrl[self._gripper_acts] = self._width
        mujoco.mj_step(self.model, self.data, nstep=steps)
