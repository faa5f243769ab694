"""One finished evaluation episode: the unit that the results store, scoring and reports exchange.

The runtime builds an `EpisodeResult` when an episode ends and hands it to the store, the progress display and,
later, to scoring. Validation happens here, once, so that a bad value (a score of 140, a typo in a dimension
id) is caught when the episode is recorded rather than silently skewing a leaderboard later.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

if TYPE_CHECKING:
    from dojo.compiler.episodes import PlannedEpisode

# A dimension is an id of the taxonomy (`dojo.compiler.taxonomy`); which ones are scored is scoring's business.
DIMENSION_ID = re.compile(r"^[a-z][a-z0-9_]*$")
# `public` rows are the leaderboard; `hidden` rows come from a suite's private verification seed set.
SPLITS: tuple[str, ...] = ("public", "hidden")


class EpisodeKey(NamedTuple):
    """What makes an episode unique inside one run; the store refuses a second row with the same key."""

    plan_hash: str
    eval_seed: int
    episode: int


def episode_key(item: PlannedEpisode) -> EpisodeKey:
    """The results store's key of a queued episode."""
    return EpisodeKey(item.plan_hash, item.eval_seed, item.episode)


@dataclass(frozen=True)
class EpisodeResult:
    """The record of one episode, exactly as it is stored (one row per episode).

    `score` is the weighted fraction of score stages reached, 0-100; `stage_times` maps each stage name to the
    step at which it was first reached, or None if it never was.
    """

    run_id: str
    split: str
    plan_hash: str
    task: str
    dimension: str
    setting: str
    eval_seed: int
    episode: int
    scene_seed: int
    policy_name: str
    success: bool
    score: float
    steps: int
    wall_time_s: float
    policy_meta: dict[str, Any] = field(default_factory=dict)
    stage_times: dict[str, int | None] = field(default_factory=dict)
    failure_reason: str | None = None
    video_path: str | None = None
    success_terms: dict[str, bool] = field(default_factory=dict)
    """Each condition of the task's success predicate at the episode's end (which one failed), when the backend
    says (the `mujoco` and `mjx` backends do)."""
    counters: dict[str, int] = field(default_factory=dict)
    """The backend's own counts over the episode, when it keeps any (the `real` backend: every command its safety
    layer clipped or refused, by kind, and its watchdog's holds), so that a trial's record says how it was run."""
    backend: str = ""
    """The backend that ran the episode: the one the run names, unless the plan required a feature that backend
    lacks and the run sent it to another (`dojo.evaluation.routing`); empty in stores written before it was kept."""

    def __post_init__(self) -> None:
        """Validate, and normalise numpy scalars (backends produce them) to plain Python values, so that what is
        stored, compared and serialised is always the same type."""
        for name in ("run_id", "plan_hash", "task", "setting", "policy_name"):
            value = getattr(self, name)
            if not isinstance(value, str) or not value:
                raise ValueError(f"EpisodeResult.{name} must be a non-empty string, got {value!r}")
        if self.split not in SPLITS:
            raise ValueError(f"EpisodeResult.split must be one of {SPLITS}, got {self.split!r}")
        if not isinstance(self.dimension, str) or not DIMENSION_ID.match(self.dimension):
            raise ValueError(f"EpisodeResult.dimension must be a dimension id (lower-case letters, digits, _), "
                             f"got {self.dimension!r}")
        for name in ("eval_seed", "episode", "scene_seed", "steps"):
            self._set(name, _integer(name, getattr(self, name)))
        if self.episode < 0 or self.steps < 0:
            raise ValueError("EpisodeResult.episode and .steps must be >= 0")
        if not isinstance(self.success, (bool, np.bool_)):
            raise ValueError(f"EpisodeResult.success must be a bool, got {self.success!r}")
        self._set("success", bool(self.success))
        self._set("score", _number("score", self.score, 0.0, 100.0))
        self._set("wall_time_s", _number("wall_time_s", self.wall_time_s, 0.0, math.inf))
        self._set("stage_times", {
            stage: None if step is None else _integer(f"stage_times[{stage!r}]", step)
            for stage, step in self.stage_times.items()
        })
        if not all(isinstance(stage, str) for stage in self.stage_times):
            raise ValueError("EpisodeResult.stage_times keys must be stage names (strings)")
        try:
            json.dumps(self.policy_meta, allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"EpisodeResult.policy_meta must be JSON data: {exc}") from exc
        if not isinstance(self.backend, str):
            raise ValueError(f"EpisodeResult.backend must be a backend name, got {self.backend!r}")
        for name in ("failure_reason", "video_path"):
            if getattr(self, name) is not None and not isinstance(getattr(self, name), str):
                raise ValueError(f"EpisodeResult.{name} must be a string or None")
        if not all(isinstance(k, str) and isinstance(v, (bool, np.bool_)) for k, v in self.success_terms.items()):
            raise ValueError("EpisodeResult.success_terms must map condition names to bools")
        self._set("success_terms", {k: bool(v) for k, v in self.success_terms.items()})
        if not all(isinstance(k, str) for k in self.counters):
            raise ValueError("EpisodeResult.counters must map counter names to integers")
        self._set("counters", {k: _integer(f"counters[{k!r}]", v) for k, v in self.counters.items()})

    def _set(self, name: str, value: Any) -> None:
        object.__setattr__(self, name, value)  # the dataclass is frozen; this runs only during construction

    @property
    def key(self) -> EpisodeKey:
        return EpisodeKey(self.plan_hash, self.eval_seed, self.episode)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (used by JSON-lines progress and the report)."""
        return asdict(self)


def _integer(name: str, value: Any) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"EpisodeResult.{name} must be an integer, got {value!r}")
    return int(value)


def _number(name: str, value: Any, low: float, high: float) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"EpisodeResult.{name} must be a number, got {value!r}")
    if not (math.isfinite(value) and low <= value <= high):
        raise ValueError(f"EpisodeResult.{name} must be finite and in [{low}, {high}], got {value!r}")
    return float(value)
