"""Images are rendered only for the slots that will look at them, with renderers kept between steps."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dojo.backends.mujoco.backend import MujocoBackend
from dojo.compiler.plan import compile_plan
from dojo.compiler.spec_library import SpecLibrary

PACK = Path(__file__).resolve().parents[1] / "specs" / "pack"


def test_step_renders_only_observed_slots() -> None:
    library = SpecLibrary.load([PACK])
    task = library.get("task", "stack_test")
    plans = [compile_plan(library, task, "standard", seed) for seed in (0, 1)]
    with MujocoBackend(num_threads=1, cameras=("head",), width=64, height=48) as backend:
        backend.load(plans)
        first = backend.reset()
        assert all(o["images"]["head"].shape == (48, 64, 3) for o in first)
        hold = np.stack([o["state"]["joint_pos"] for o in first])
        result = backend.step(hold, [0, 1], observe=[1])
        assert "images" not in result.obs[0]
        assert result.obs[1]["images"]["head"].dtype == np.uint8
        kept = [r for _, r in backend._renderers._renderers.values()]
        again = backend.step(hold, [0, 1])  # observe=None: every slot
        assert all("images" in o for o in again.obs)
        assert [r for _, r in backend._renderers._renderers.values()] == kept  # one renderer per model, reused
