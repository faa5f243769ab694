"""Where the robot lives in a compiled MuJoCo model, its proprioception, and forward kinematics for the IK.

`RobotIndex.build(model, robot)` resolves the plan's `robot` handles (names, see dojo/compiler/robot_emit.py) to
ids and addresses once per model. The state layout is the joint action layout: `[left joints, left gripper,
right joints, right gripper]`, grippers normalised 0 (closed) .. 1 (open) from the width tendon's length.
End-effector poses are expressed in each arm's base frame (the `<arm>_base` body), as in the ee action mode.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from dojo.backends.actions import ArmLimits


@dataclass(frozen=True)
class RobotIndex:
    """Ids and addresses of the robot's parts in one model, arms first axis (left, right)."""

    qpos_adr: np.ndarray      # [2, J] arm joints' qpos addresses
    dof_adr: np.ndarray       # [2, J] arm joints' dof addresses
    tendons: np.ndarray       # [2] gripper width tendons
    ee_sites: np.ndarray      # [2]
    bases: np.ndarray         # [2] base bodies
    actuators: np.ndarray     # [2 (J + 1)] actuator ids in action order
    limits: ArmLimits

    @classmethod
    def build(cls, model: mujoco.MjModel, robot: dict[str, Any]) -> RobotIndex:
        arms = list(robot["arms"])
        joints = np.asarray([model.joint(j).id for j in robot["arm_joints"]]).reshape(len(arms), -1)
        lo, hi = model.jnt_range[joints, 0], model.jnt_range[joints, 1]
        return cls(
            qpos_adr=model.jnt_qposadr[joints],
            dof_adr=model.jnt_dofadr[joints],
            tendons=np.asarray([model.tendon(t).id for t in robot["gripper_tendons"]]),
            ee_sites=np.asarray([model.site(s).id for s in robot["ee_sites"]]),
            bases=np.asarray([model.body(f"{arm}_base").id for arm in arms]),
            actuators=np.asarray([model.actuator(a).id for a in robot["actuators"]]),
            limits=ArmLimits(joint_lo=lo, joint_hi=hi, max_width=float(robot["gripper_max_width"])),
        )

    def arm_q(self, data: mujoco.MjData) -> np.ndarray:
        """Measured arm joint positions [2, J]."""
        return data.qpos[self.qpos_adr]

    def gripper(self, data: mujoco.MjData) -> np.ndarray:
        """Gripper openings [2], 0 closed .. 1 open."""
        return np.clip(data.ten_length[self.tendons] / self.limits.max_width, 0.0, 1.0)

    def ee_pose(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """End-effector positions [2, 3] and rotations [2, 3, 3] in the arms' base frames."""
        base_r = data.xmat[self.bases].reshape(2, 3, 3)
        world_p = data.site_xpos[self.ee_sites]
        world_r = data.site_xmat[self.ee_sites].reshape(2, 3, 3)
        pos = np.einsum("aji,aj->ai", base_r, world_p - data.xpos[self.bases])
        return pos, np.swapaxes(base_r, -1, -2) @ world_r

    def ee_quat(self, rot: np.ndarray) -> np.ndarray:
        """Quaternions [2, 4] (w >= 0) of ee rotations [2, 3, 3], with MuJoCo's C routine (this runs for every
        observation; `rotations.mat_to_quat` is the batched array version of the same)."""
        quat = np.empty((2, 4))
        for arm in range(2):
            mujoco.mju_mat2Quat(quat[arm], rot[arm].ravel())
        return quat * np.where(quat[:, :1] < 0, -1.0, 1.0)

    def proprioception(self, data: mujoco.MjData) -> dict[str, np.ndarray]:
        """The observation's `state`: joint_pos, joint_vel [14], ee_pose [2, 7], gripper [2] (float32)."""
        grip = self.gripper(data)
        grip_vel = data.ten_velocity[self.tendons] / self.limits.max_width
        pos, rot = self.ee_pose(data)
        joint_pos = np.concatenate([self.arm_q(data), grip[:, None]], axis=1).ravel()
        joint_vel = np.concatenate([data.qvel[self.dof_adr], grip_vel[:, None]], axis=1).ravel()
        return {
            "joint_pos": joint_pos.astype(np.float32),
            "joint_vel": joint_vel.astype(np.float32),
            "ee_pose": np.concatenate([pos, self.ee_quat(rot)], axis=1).astype(np.float32),
            "gripper": grip.astype(np.float32),
        }


class ArmKinematics:
    """Forward kinematics of both arms on a scratch MjData, in the callback form `actions.solve_ik` takes.

    The scratch copy holds the environment's current state, so only the arm joints change between calls and
    the simulation's own MjData is never touched by the IK.
    """

    def __init__(self, model: mujoco.MjModel, index: RobotIndex) -> None:
        self.model, self.index = model, index
        self.scratch = mujoco.MjData(model)
        self._jacp = np.zeros((3, model.nv))
        self._jacr = np.zeros((3, model.nv))

    def sync(self, data: mujoco.MjData) -> None:
        """Take the environment's current positions (bases, objects and all) into the scratch data."""
        self.scratch.qpos[:] = data.qpos

    def __call__(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        m, d, ix = self.model, self.scratch, self.index
        d.qpos[ix.qpos_adr] = q
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        pos, rot = ix.ee_pose(d)
        base_r = d.xmat[ix.bases].reshape(2, 3, 3)
        jac = np.empty((2, 6, ix.qpos_adr.shape[1]))
        for arm in range(2):
            mujoco.mj_jacSite(m, d, self._jacp, self._jacr, int(ix.ee_sites[arm]))
            cols = ix.dof_adr[arm]
            jac[arm, :3] = base_r[arm].T @ self._jacp[:, cols]
            jac[arm, 3:] = base_r[arm].T @ self._jacr[:, cols]
        return pos, rot, jac
