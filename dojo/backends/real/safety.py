"""The safety layer between the policy and the driver: every command is checked, clipped or refused, and counted.

Per command (one control step's joint targets [2, J] and grippers [2]), in this order:
1. during an e-stop (holding, returning, or stopped at the reset pose) every command is refused;
2. a non-finite value is refused;
3. a target farther than `max_jump` from the measured joints (any joint) is refused: a policy that far off
   would still be driven there step by step if it were only clipped;
4. targets are clipped to the joint ranges and grippers to [0, 1];
5. the step from the previous command is clipped to the joints' velocity limits, and its speed-up to their
   accelerations (slowing down is never limited, so a clipped command never overshoots its target);
6. the result is posed on the robot's collision model (`workspace.RobotGeometry`): a target that puts any
   moving geom below the table plane (beyond `table_penetration`) or outside the workspace box, or brings the
   two arms closer to each other than `arm_clearance`, is refused.
What passes is sent; a refused command sends nothing, so the arms keep the last safe target.

A supervisor (thread, `start()`) runs `tick` at SUPERVISOR_HZ: with no command for `watchdog_s` it holds the
arms where they are; after an e-stop it holds for `estop_hold_s`, then returns the arms to the reset pose at
`return_speed` of their joint speeds (through the driver's own interpolation) and waits there, stopped, until
the operator calls `release()`.

`estop()` commands the hold at once, from the caller's thread, and waits for nothing the control loop holds:
checking a command (the collision model, the driver's state) happens under one lock, sending it under a second,
short one, and the e-stop takes neither before its hold goes out. It raises the halt flag (every command not yet
sent is refused from then on), sends the hold, then takes the send lock, behind a command that was already being
sent, and sends the hold again, so that no command of the policy's can follow it. Under load, a control loop
that holds its lock while the OS or the GIL has it waiting would otherwise delay the e-stop by that much (once
253 ms on the shared 2-core machine, where the hold itself goes out in about a millisecond).

An e-stop may also come from another process with a connection of its own to the arms (the console's,
`dojo.realeval.estop`): it raises `remote_halt`, a flag shared with this process, before it sends its hold, so
that from then on every command is refused here as after `estop()`, and then says so, on which the console calls
`estop()` (which holds again and begins the return).

Every clipped or refused command is counted per trial (`counters`, names in COUNTERS), for the operator
console and the trial's record; `new_trial()` zeroes them.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from dojo.backends.real.driver import Driver
from dojo.backends.real.robot_config import RealRobotConfig
from dojo.backends.real.workspace import RobotGeometry

COUNTERS = ("refused_estop", "refused_nonfinite", "refused_jump", "refused_table", "refused_workspace",
            "refused_arm_collision", "clipped_joint_limit", "clipped_gripper", "clipped_velocity",
            "clipped_acceleration", "watchdog_holds")
SUPERVISOR_HZ = 100.0
HOME_TOLERANCE = 0.01
"""rad: the return to the reset pose is over when every joint is this close to it."""

RUNNING, HOLDING, ESTOP, RETURNING, STOPPED = "running", "holding", "estop", "returning", "stopped"


@dataclass(frozen=True)
class Verdict:
    """What became of one command: `sent` or not, the clip counters it raised, the refusal counter (or None)."""

    sent: bool
    clipped: tuple[str, ...] = ()
    refused: str | None = None


class SafetyLayer:
    """Checks every command for `driver` against the limits of `config` on the collision model `geometry`."""

    def __init__(self, driver: Driver, geometry: RobotGeometry, config: RealRobotConfig, control_hz: float,
                 clock: Callable[[], float] = time.monotonic) -> None:
        """`control_hz`: the rate commands come at (velocity and acceleration limits are per its period);
        `clock`: monotonic seconds, for the watchdog and the e-stop's hold."""
        self.driver, self.geometry, self.config, self.clock = driver, geometry, config, clock
        self.dt = 1.0 / control_hz
        limits = geometry.index.limits
        self.joint_lo, self.joint_hi = limits.joint_lo, limits.joint_hi
        self.counters = dict.fromkeys(COUNTERS, 0)
        self.estop_time: float | None = None
        self._halt = threading.Event()
        self._halt_state = ESTOP
        self._run_state = RUNNING
        self._lock = threading.Lock()
        """Held while a command is checked (and by the supervisor's tick)."""
        self._send_lock = threading.Lock()
        """Held while anything is sent to the driver after its checks; the e-stop's first hold does not wait."""
        self._last_command: float | None = None
        self._prev_q = self._prev_v = np.zeros_like(self.joint_lo)  # set at rest by the first command
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.remote_halt: Any = None
        """A flag shared with another process (e.g. a `multiprocessing` Value): true while its e-stop is in
        force (see the module docstring)."""

    @property
    def halted(self) -> bool:
        """An e-stop is in force (holding, returning, or stopped at the reset pose) until `release()`."""
        return self._halt.is_set() or bool(self.remote_halt is not None and self.remote_halt.value)

    @property
    def state(self) -> str:
        """RUNNING or HOLDING (the watchdog's), else during an e-stop ESTOP, RETURNING or STOPPED."""
        return self._halt_state if self._halt.is_set() else self._run_state

    # ---- trials ----

    def new_trial(self) -> None:
        """Zero the counters; the watchdog sleeps until the trial's first command, which is limited from
        wherever the arms are then, at rest (so the robot may be moved to its start in between). An e-stop
        stays in force until `release()`."""
        with self._lock:
            self.counters = dict.fromkeys(COUNTERS, 0)
            self._last_command = None

    def release(self) -> None:
        """The operator's go-ahead after an e-stop: accept commands again, from where the arms are then."""
        with self._lock, self._send_lock:
            self._run_state, self._halt_state, self.estop_time, self._last_command = RUNNING, ESTOP, None, None
            self._halt.clear()
            if self.remote_halt is not None:
                self.remote_halt.value = 0

    # ---- commands ----

    def command(self, joint_pos: np.ndarray, gripper: np.ndarray) -> Verdict:
        """Check one command (see the module docstring) and send it if it passes."""
        q = np.asarray(joint_pos, dtype=float).reshape(self.joint_lo.shape)
        grip = np.asarray(gripper, dtype=float).reshape(2)
        with self._lock:
            if self.halted:
                return self._refuse("refused_estop")
            if not (np.isfinite(q).all() and np.isfinite(grip).all()):
                return self._refuse("refused_nonfinite")
            if self._run_state == HOLDING or self._last_command is None:
                self._rest_at_measured()
            if np.abs(q - self.driver.read().joint_pos).max() > self.config.max_jump:
                return self._refuse("refused_jump")
            clipped = []
            limited = np.clip(q, self.joint_lo, self.joint_hi)
            if not np.array_equal(limited, q):
                clipped.append("clipped_joint_limit")
            grip_ok = np.clip(grip, 0.0, 1.0)
            if not np.array_equal(grip_ok, grip):
                clipped.append("clipped_gripper")
            limited, velocity, rate_clips = self._rate_limit(limited)
            clipped += rate_clips
            refusal = self._placement(limited, grip_ok)
            if refusal is not None:
                self._prev_v = np.zeros_like(self._prev_v)  # the arms stop at the last safe target
                return self._refuse(refusal)
            with self._send_lock:
                if self.halted:  # the e-stop came while this command was being checked
                    return self._refuse("refused_estop")
                self.driver.command(limited, grip_ok)
                self._prev_q, self._prev_v = limited, velocity
                self._last_command = self.clock()
                self._run_state = RUNNING
            for name in clipped:
                self.counters[name] += 1
            return Verdict(sent=True, clipped=tuple(clipped))

    def _rate_limit(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """q with its step from the previous command limited in velocity and in speed-up; the new velocity."""
        wanted = (q - self._prev_q) / self.dt
        vmax = self.config.joint_velocity
        v = np.clip(wanted, -vmax, vmax)
        clips = ["clipped_velocity"] if not np.array_equal(v, wanted) else []
        same_way = np.sign(v) == np.sign(self._prev_v)
        allowed = np.where(same_way, np.abs(self._prev_v), 0.0) + self.config.joint_acceleration * self.dt
        slower = np.sign(v) * np.minimum(np.abs(v), allowed)
        if not np.array_equal(slower, v):
            clips.append("clipped_acceleration")
        if not clips:
            return q, slower, clips
        return self._prev_q + slower * self.dt, slower, clips

    def _placement(self, q: np.ndarray, gripper: np.ndarray) -> str | None:
        """The refusal counter if the robot's collision model at (q, gripper) leaves the allowed space."""
        lo, hi = self.geometry.boxes(q, gripper)
        if lo[:, 2].min() < self.config.table_z - self.config.table_penetration:
            return "refused_table"
        if (lo < self.config.workspace_lo).any() or (hi > self.config.workspace_hi).any():
            return "refused_workspace"
        if self.geometry.arms_gap(lo, hi, self.config.arm_clearance) < self.config.arm_clearance:
            return "refused_arm_collision"
        return None

    def _refuse(self, counter: str) -> Verdict:
        self.counters[counter] += 1
        return Verdict(sent=False, refused=counter)

    def _rest_at_measured(self) -> None:
        self._prev_q = self.driver.read().joint_pos
        self._prev_v = np.zeros_like(self._prev_q)

    # ---- e-stop and supervision ----

    def estop(self) -> float:
        """Disable policy control and hold the arms now, without waiting for the control loop (see the module
        docstring); the supervisor returns them to the reset pose after `estop_hold_s`. Returns the trigger time
        (on `clock`)."""
        trigger = self.clock()
        self._halt_state, self.estop_time = ESTOP, trigger
        self._halt.set()
        self.driver.hold()
        with self._send_lock:  # behind a command that was already being sent: hold again, after it
            self.driver.hold()
            self._halt_state, self.estop_time = ESTOP, trigger  # over a return the supervisor began meanwhile
        return trigger

    def tick(self, now: float) -> None:
        """One supervisor step at time `now` (the thread calls it; tests may call it with their own times)."""
        with self._lock, self._send_lock:
            if not self.halted:
                if self._run_state == RUNNING and self._last_command is not None \
                        and now - self._last_command > self.config.watchdog_s:
                    self.driver.hold()
                    self.counters["watchdog_holds"] += 1
                    self._run_state = HOLDING
            elif self._halt_state == ESTOP and self.estop_time is not None \
                    and now - self.estop_time >= self.config.estop_hold_s:
                self.driver.home(self.config.return_speed)
                self._halt_state = RETURNING
            elif self._halt_state == RETURNING:
                home = self.driver.home_pose[0]
                if np.abs(self.driver.read().joint_pos - home).max() < HOME_TOLERANCE:
                    self._halt_state = STOPPED

    def start(self) -> None:
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._supervise, name="dojo-safety", daemon=True)
            self._thread.start()

    def close(self) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            self._thread = None

    def _supervise(self) -> None:
        while not self._stop.wait(1.0 / SUPERVISOR_HZ):
            self.tick(self.clock())
