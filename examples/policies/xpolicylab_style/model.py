"""A policy written the XPolicyLab way (a plain class, one config dict, no RoboDojo base class), served unchanged:

    xpolicylab serve policy=examples/policies/xpolicylab_style/model.py
    xpolicylab check url=ws://127.0.0.1:19000

It moves both grippers towards open while holding the arm joints, one chunk of ``chunk_size`` steps at a time.
"""

from __future__ import annotations

import numpy as np


class Model:
    def __init__(self, deploy_cfg: dict) -> None:
        self.chunk_size = int(deploy_cfg.get("chunk_size", 8))
        self.obs: dict | None = None

    @property
    def metadata(self) -> dict:
        return {"name": "xpolicylab_style", "action_mode": "joint", "chunk_size": self.chunk_size,
                "action_dim": 14, "cameras": ["head"], "image_width": None, "image_height": None}

    def reset(self) -> None:
        self.obs = None

    def update_obs(self, obs: dict) -> None:
        self.obs = obs

    def get_action(self) -> np.ndarray:
        pose = np.asarray(self.obs["state"]["joint_pos"], dtype=np.float32)
        chunk = np.repeat(pose[None], self.chunk_size, axis=0)
        opening = np.linspace(0.0, 1.0, self.chunk_size, dtype=np.float32)
        for gripper in (6, 13):
            chunk[:, gripper] = pose[gripper] + (1.0 - pose[gripper]) * opening
        return chunk
