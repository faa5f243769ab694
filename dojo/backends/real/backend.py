"""The real backend: a plan's instruction and horizon run on a robot (or its emulator) through the safety layer.

One robot is one slot: `load` takes exactly one plan. Every control step, the action (any of the four modes;
end-effector poses through the same damped-least-squares IK as in simulation, on the plan's model) becomes
joint targets, the safety layer clips or refuses them (`SafetyLayer`), and the step lasts one control period
of wall-clock time. Observations are the standard envelope (`dojo.backends.base`): the arms' state as the
driver reports it, end-effector poses by forward kinematics of the reported joints, camera images.

What the robot cannot know is left to the RealEval protocol: success and score are given by the raters
afterwards (a step reports neither; stage times stay unset), so an episode ends at its horizon, or on a
non-finite action as in simulation, or by the operator: an e-stop (`END_ESTOP`) or a stop (`request_stop()`,
`END_OPERATOR_STOP`) ends it at the next step, which commands nothing. `clipped` counts the step's clips and
refusals (safety layer and IK goal);
the safety layer's own counters (watchdog holds included) are `backend.safety.counters`, reported with every
step (`StepResult.counters`) so that each trial's row in the results store keeps them.

`driver="emulator"` (the default) runs the plan's own scene in the emulator (`EmulatedRobot`), through the
maker's SDK as on hardware; a reset puts the scene at the plan's initial state, as the operator would.
`driver="piper"` runs the hardware on the CAN buses `can` (default: the robot's configuration); a reset
returns the arms to the reset pose slowly, and the scene is the operator's to lay out. Cameras come from
`sources` (`backend.cameras`, see `cameras`): the emulator's by default, USB cameras through OpenCV/V4L2 or
RealSense cameras on hardware; they are opened before the arms are connected. An e-stop (`backend.safety.estop()`, from any thread) stays in force across resets until
`backend.safety.release()`.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from typing import Any

import mujoco
import numpy as np

from dojo.backends import actions as A
from dojo.backends.base import END_HORIZON, END_NONFINITE, Backend, EpisodeDone, Observation, StepResult, checked_actions, envelope, resolve_ids
from dojo.backends.mujoco.kinematics import ArmKinematics, RobotIndex
from dojo.backends.real.cameras import CameraSource, open_cameras, parse_sources
from dojo.backends.real.driver import Driver
from dojo.backends.real.emulator import EmulatedRobot, EmulatorParams
from dojo.backends.real.robot_config import RealRobotConfig
from dojo.backends.real.safety import SafetyLayer
from dojo.backends.real.workspace import RobotGeometry

DRIVERS = ("emulator", "piper")
END_ESTOP = "estop"
END_OPERATOR_STOP = "operator_stop"
SETTLE_TIMEOUT_S = 60.0
"""Longest a reset waits for the arms to reach the episode's start pose."""
AT_POSE = 0.01
"""rad: the arms are at a pose when every joint is this close."""


class RealBackend(Backend):
    """One robot (or its emulator), one slot. See the module docstring for what a step does."""

    name = "real"
    max_envs = 1

    def __init__(self, driver: str = "emulator", can: str | Sequence[str] | None = None,
                 cameras: Sequence[str] = (), width: int = 640, height: int = 480, depth: bool = False,
                 emulator: Mapping[str, Any] | None = None, sources: Any = "emulator") -> None:
        """`driver`: `emulator` or `piper`; `can`: the left and right arm's CAN buses (a list, or one string
        `left,right`); `cameras` at width x height, each from its source in `sources` (the `backend.cameras`
        setting); `emulator`: `EmulatorParams` fields."""
        if driver not in DRIVERS:
            raise ValueError(f"backend real: unknown driver {driver!r}; one of {', '.join(DRIVERS)}")
        self.driver_name = driver
        self.can = tuple(can.split(",")) if isinstance(can, str) else tuple(can or ())
        self.camera_names, self.width, self.height, self.depth = tuple(cameras), width, height, depth
        self.emulator_params = EmulatorParams(**dict(emulator or {}))
        self.sources = parse_sources(sources, self.camera_names)
        self.safety: SafetyLayer | None = None
        self._plan: Any = None
        self._embodiment: str | None = None
        self._emulated: EmulatedRobot | None = None
        self._driver: Driver | None = None
        self._cameras: CameraSource | None = None
        self._kinematics: ArmKinematics | None = None
        self._scene: mujoco.MjModel | None = None
        self._step = 0
        self._done, self._end_reason, self._clipped_total = False, None, 0
        self._next_step = 0.0
        self._stop_requested = False

    @property
    def num_envs(self) -> int:
        return 0 if self._plan is None else 1

    # ---- plans and episodes ----

    def load(self, plans: Sequence[Any]) -> None:
        if len(plans) != 1:
            raise ValueError(f"backend real runs one robot: load one plan at a time, got {len(plans)}")
        self._switch(plans[0])
        self._restart()

    def reset(self, env_ids: Sequence[int] | None = None, plans: Sequence[Any] | None = None) -> list[Observation]:
        ids = resolve_ids(env_ids, self.num_envs)
        if plans is not None:
            if len(plans) != ids.size:
                raise ValueError(f"reset got {len(plans)} plans for {ids.size} env_ids")
            if ids.size:
                self._switch(plans[0])
        if ids.size:
            self._restart()
        return [self._observation(images=True) for _ in ids]

    def _switch(self, plan: Any) -> None:
        """Make `plan` the slot's plan. The first plan connects the robot; later plans must share its
        embodiment (one robot). The robot's kinematics come from the first plan's model (a scene does not change
        them); the emulator takes each plan's own scene."""
        if self._embodiment is not None and plan.embodiment != self._embodiment:
            raise ValueError(f"backend real runs one robot ({self._embodiment}); got a plan for {plan.embodiment}")
        if self._driver is None:
            self._connect(plan)
        elif self._emulated is not None:
            self._scene = plan.model()
        self._plan = plan

    def _connect(self, plan: Any) -> None:
        model = self._scene = plan.model()
        config = RealRobotConfig.load(plan.embodiment)
        if self.driver_name == "emulator":
            self._emulated = EmulatedRobot(model, plan.robot, config, self.emulator_params, plan.init_qpos)
            self._driver = self._emulated.driver()
        elif config.driver == "piper":
            from dojo.backends.real.piper_driver import PiperDriver

            self._driver = PiperDriver(plan.robot, self.can or config.can, interface="socketcan")
        else:
            raise ValueError(f"backend real: robot {config.robot} has no hardware driver yet (driver "
                             f"{config.driver}; see dojo/backends/real/robots/{config.robot}.yaml); run it with "
                             "backend.driver=emulator")
        if self.camera_names:
            emulated = self._emulated
            self._cameras = open_cameras(
                self.sources, self.width, self.height, self.depth,
                None if emulated is None else lambda names: emulated.cameras(names, self.width, self.height,
                                                                             self.depth))
        self._driver.connect()
        self._embodiment = plan.embodiment
        self._kinematics = ArmKinematics(model, RobotIndex.build(model, plan.robot))
        self.safety = SafetyLayer(self._driver, RobotGeometry(model, plan.robot), config, plan.control_hz)
        self.safety.start()

    def _restart(self) -> None:
        """Begin a new trial of the safety layer and put the robot at the episode's start (the emulator: the
        plan's initial scene; hardware: the reset pose, slowly)."""
        self.safety.new_trial()
        if self._emulated is not None:
            self._emulated.sim.load(self._scene, self._plan.robot, self._plan.init_qpos)
            start = np.asarray(self._plan.init_qpos)[RobotIndex.build(self._scene, self._plan.robot).qpos_adr]
        else:
            start = self._driver.home_pose[0]
            self._driver.home(self.safety.config.return_speed)
        self._wait_at(start)
        self._step, self._done, self._end_reason, self._clipped_total = 0, False, None, 0
        self._stop_requested = False
        self._next_step = time.monotonic()

    def _wait_at(self, joint_pos: np.ndarray) -> None:
        deadline = time.monotonic() + SETTLE_TIMEOUT_S
        while np.abs(self._driver.read().joint_pos - joint_pos).max() > AT_POSE:
            if time.monotonic() > deadline:
                raise TimeoutError(f"backend real: the arms did not reach the start pose in {SETTLE_TIMEOUT_S} s")
            time.sleep(0.005)

    # ---- stepping ----

    def step(self, actions: np.ndarray, env_ids: Sequence[int] | None = None, mode: str = "joint",
             observe: Sequence[int] | None = None) -> StepResult:
        ids = resolve_ids(env_ids, self.num_envs)
        if not ids.size:
            return self._result(ids, [], 0)
        if self._done:
            raise EpisodeDone(f"the episode ended ({self._end_reason}); reset before stepping")
        if self.safety.halted or self._stop_requested:  # the operator ended the trial: command nothing more
            self._done, self._end_reason = True, END_ESTOP if self.safety.halted else END_OPERATOR_STOP
            return self._result(ids, [self._observation(observe is None or 0 in set(observe))], 0)
        joints = self._kinematics.index.limits.joints_per_arm
        actions = checked_actions(actions, mode, 1, joints)
        if A.nonfinite(np, actions)[0]:  # the safety layer refuses and counts it; the episode ends, as in sim
            verdict = self.safety.command(np.full((2, joints), np.nan), np.full(2, np.nan))
            self._done, self._end_reason, ik_clips = True, END_NONFINITE, 0
        else:
            q, grip, ik_clips = self._targets(actions, mode)
            verdict = self.safety.command(q, grip)
            self._pace()
            self._step += 1
            if self._step >= self._plan.horizon:
                self._done, self._end_reason = True, END_HORIZON
        clips = len(verdict.clipped) + (verdict.refused is not None) + ik_clips
        self._clipped_total += clips
        return self._result(ids, [self._observation(observe is None or 0 in set(observe))], clips)

    def request_stop(self) -> None:
        """End the running trial at its next step (the operator's Stop; from any thread). The arms keep their
        last target, and the watchdog holds them."""
        self._stop_requested = True

    def _targets(self, actions: np.ndarray, mode: str) -> tuple[np.ndarray, np.ndarray, int]:
        """Joint targets [2, J], grippers [2] and the IK goal's clipped count (0 for joint modes)."""
        state = self._driver.read()
        joints = state.joint_pos.shape[1]
        if mode in ("joint", "delta_joint"):
            a = actions.reshape(2, joints + 1)
            return a[:, :joints] + (state.joint_pos if mode == "delta_joint" else 0.0), a[:, joints], 0
        kin = self._kinematics
        pos_now, rot_now, _ = kin(state.joint_pos)
        quat_now = kin.index.ee_quat(rot_now)
        pos, rot, grip, clipped = A.ee_targets(np, actions, pos_now[None], quat_now[None], kin.index.limits,
                                               delta=mode == "delta_ee")
        q = A.solve_ik(np, kin, state.joint_pos, pos[0], rot[0], kin.index.limits.joint_lo,
                       kin.index.limits.joint_hi, tol=A.IK_TOLERANCE)
        return q, grip[0], int(clipped[0])

    def _pace(self) -> None:
        """Hold the step to one control period of wall-clock time (never catching up on a late step)."""
        self._next_step += 1.0 / self._plan.control_hz
        now = time.monotonic()
        if self._next_step > now:
            time.sleep(self._next_step - now)
        else:
            self._next_step = now

    # ---- observations and results ----

    def _observation(self, images: bool) -> Observation:
        plan, state = self._plan, self._driver.read()
        pos, rot, _ = self._kinematics(state.joint_pos)
        quat = self._kinematics.index.ee_quat(rot)
        grip = state.gripper[:, None]
        obs = envelope(plan, self._step, {
            "joint_pos": np.concatenate([state.joint_pos, grip], axis=1).ravel().astype(np.float32),
            "joint_vel": np.concatenate([state.joint_vel, np.zeros_like(grip)], axis=1).ravel().astype(np.float32),
            "ee_pose": np.concatenate([pos, quat], axis=1).astype(np.float32),
            "gripper": state.gripper.astype(np.float32),
        })
        if self._cameras is not None and images:
            frames = self._cameras.frames()
            obs["images"] = {c: frames[c] for c in self.camera_names}
            if self.depth:
                obs["depth"] = {c: frames[f"{c}_depth"] for c in self.camera_names}
        return obs

    def _result(self, ids: np.ndarray, obs: list[Observation], clipped: int) -> StepResult:
        n = ids.size
        stages = [s["name"] for s in self._plan.program.get("stages", [])] if self._plan is not None else []
        return StepResult(
            env_ids=ids, obs=obs, success=np.zeros(n, dtype=bool), score=np.zeros(n, dtype=np.float32),
            done=np.full(n, self._done), steps=np.full(n, self._step, dtype=np.int32),
            stage_times=[dict.fromkeys(stages) for _ in range(n)], end_reason=[self._end_reason] * n,
            clipped=np.full(n, clipped, dtype=np.int32), clipped_total=np.full(n, self._clipped_total, dtype=np.int32),
            counters=[dict(self.safety.counters) for _ in range(n)] if self.safety is not None else [],
        )

    def close(self) -> None:
        if self.safety is not None:
            self.safety.close()
        if self._driver is not None:
            self._driver.close()
        if self._cameras is not None:
            self._cameras.close()
        if self._emulated is not None:
            self._emulated.close()

