"""Auto horizons: the 90th percentile of demo lengths x 1.2 (x 1.5 auto-generated), else the declared fallback."""

from __future__ import annotations

import json
from pathlib import Path

from dojo.compiler.horizon import HORIZONS_FORMAT, auto_horizon, load_demo_lengths, task_horizon
from dojo.compiler.plan import plan_hash
from dojo.compiler.spec_library import SpecLibrary


def test_auto_horizon_by_hand() -> None:
    lengths = list(range(1, 101))  # p90 with linear interpolation = 90.1
    assert auto_horizon(lengths) == 109  # ceil(90.1 x 1.2 = 108.12)
    assert auto_horizon(lengths, auto_generated=True) == 136  # ceil(135.15)
    assert auto_horizon([100] * 10) == 120  # exactly 120, not 121


def test_task_horizon_uses_demos_when_present() -> None:
    task = {"horizon": "auto", "horizon_fallback": 400}
    assert task_horizon(task) == 400
    assert task_horizon(task, [200] * 5) == 240
    assert task_horizon({"horizon": 300}, [200] * 5) == 300


def test_demo_lengths_change_the_plan_hash(tmp_path: Path) -> None:
    path = tmp_path / "horizons.json"
    path.write_text(json.dumps({"format": HORIZONS_FORMAT, "tasks": {"stack_blocks": {"demo_lengths": [300, 320]}}}))
    demos = load_demo_lengths(path)
    library = SpecLibrary.load()
    task = library.get("task", "stack_blocks")
    assert plan_hash(library, task, "standard", 0, demos["stack_blocks"]) != plan_hash(library, task, "standard", 0)
