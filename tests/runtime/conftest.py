"""Factories for episode rows shared by the runtime tests."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest

from dojo.evaluation.episode import EpisodeResult

RowFactory = Callable[..., EpisodeResult]


def _make_row(**overrides: Any) -> EpisodeResult:
    fields: dict[str, Any] = dict(
        run_id="run-a", split="public", plan_hash="p0", task="stack_bowls", dimension="generalization",
        setting="standard", eval_seed=0, episode=0, scene_seed=1000, policy_name="policy-a", success=False,
        score=0.0, steps=100, wall_time_s=1.5, policy_meta={"checkpoint": "ckpt-1"}, stage_times={},
    )
    fields.update(overrides)
    if "plan_hash" not in overrides:  # one plan per (task, setting, split, episode), like the compiler's
        fields["plan_hash"] = f"{fields['task']}-{fields['setting']}-{fields['split']}-{fields['episode']}"
    return EpisodeResult(**fields)


@pytest.fixture
def make_row() -> RowFactory:
    """`make_row(task=..., success=..., ...)`: a valid EpisodeResult with sensible defaults."""
    return _make_row


@pytest.fixture
def make_task_rows() -> Callable[..., list[EpisodeResult]]:
    """`make_task_rows(task, dimension, outcomes, **common)`: one row per (success, score) outcome, episode
    indices counting from `first_episode`."""

    def build(task: str, dimension: str, outcomes: list[tuple[bool, float]], first_episode: int = 0,
              **common: Any) -> list[EpisodeResult]:
        return [
            _make_row(task=task, dimension=dimension, episode=first_episode + i, success=s, score=sc, **common)
            for i, (s, sc) in enumerate(outcomes)
        ]

    return build
