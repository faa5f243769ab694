"""The records of an episode before it runs: its place in the protocol, and that place with the plan that runs it.

`Episode` is what the protocol asks for (task, setting, scene seed, evaluation seed, number); `PlannedEpisode` adds
the plan compiled for it and the split it is scored in, and is what the compiler hands the evaluation loop, the
Ray dispatcher, the recorder and routing, typed (no file parsed back). The evaluation loop turns a finished one
into an `EpisodeResult` row. This module imports nothing heavy, so light callers can name the records.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Episode:
    """One episode of the protocol: which task, setting and scene, under which evaluation seed, and its number
    among that task's episodes of the seed."""

    task: str
    dimension: str
    setting: str
    scene_seed: int
    eval_seed: int
    episode: int


@dataclass(frozen=True)
class PlannedEpisode(Episode):
    """An episode with the plan that runs it (`plan_hash`, the file at `plan_path`) and its split: `public` rows
    are the leaderboard, `hidden` rows come from a suite's private verification seed set."""

    plan_hash: str
    plan_path: Path
    split: str = "public"
