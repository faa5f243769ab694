"""Episode horizons: a task's own number, or `auto` from the lengths of its demonstrations.

DESIGN section 4: `auto` = the 90th percentile of the demo lengths x 1.2 (x 1.5 for short auto-generated tasks),
using the demos' lengths when present and the task's declared `horizon_fallback` otherwise. The lengths come from
`dojo collect`, which merges them into one horizons file per project (`datasets/horizons.json` by default, every
collected task in one file), and `dojo compile` and `dojo run` read that same file by default, so collecting demos
is enough for the suite to use their horizons. The horizon is an input of the plan hash: new demos, new plans.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

HORIZONS_FORMAT = "robodojo-horizons/1"
DEFAULT_HORIZONS = Path("datasets") / "horizons.json"
"""Where `dojo collect` writes demo lengths and `dojo compile` / `dojo run` read them (relative to the working
directory, like `outputs/`)."""


def auto_horizon(lengths: list[int], auto_generated: bool = False) -> int:
    """90th percentile of `lengths` x 1.2 (x 1.5 when `auto_generated`), rounded up to a whole control step."""
    if not lengths:
        raise ValueError("auto_horizon needs at least one demo length")
    p90 = float(np.percentile(np.asarray(lengths, dtype=np.float64), 90))
    return math.ceil(round(p90 * (1.5 if auto_generated else 1.2), 6))  # 100 x 1.2 is 120, not 121


def horizons_file(setting: str | None) -> Path | None:
    """The horizons file a `horizons=` setting names: `auto` is DEFAULT_HORIZONS when it exists (no demos
    collected yet: none), null is none, anything else a path that must exist."""
    if setting is None:
        return None
    if setting == "auto":
        return DEFAULT_HORIZONS if DEFAULT_HORIZONS.exists() else None
    path = Path(setting)
    if not path.exists():
        raise FileNotFoundError(f"horizons={setting}: no such file (dojo collect writes one; horizons=null for none)")
    return path


def load_demo_lengths(path: Path | None) -> dict[str, list[int]]:
    """Task id -> demo lengths, from a horizons file written by `dojo collect` (empty without a file)."""
    if path is None:
        return {}
    data = json.loads(Path(path).read_text())
    if data.get("format") != HORIZONS_FORMAT:
        raise ValueError(f"{path}: not a {HORIZONS_FORMAT} file")
    return {task: [int(n) for n in entry["demo_lengths"]] for task, entry in data["tasks"].items()}


def task_horizon(task: dict, demo_lengths: list[int] | None = None) -> int:
    """The horizon in control steps of a (validated) task spec."""
    if task["horizon"] != "auto":
        return int(task["horizon"])
    if demo_lengths:
        return auto_horizon(demo_lengths, bool(task.get("auto_generated", False)))
    return int(task["horizon_fallback"])
