"""Which backend runs which episode: a plan goes to the backend the run names unless that backend cannot run a
feature the plan requires (`plan.requires`); then it goes to the fallback backend, and the run says so.

Nothing is routed silently: every move is a `Detour` naming the task, how many episodes, the features and the
backend's reasons, which `dojo run` prints before it starts. A plan that neither backend can run stops the run
before any episode does, naming what is missing.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from dojo.backends.registry import unsupported_features
from dojo.compiler.episodes import PlannedEpisode

FALLBACK = "mujoco"
"""The CPU reference backend, which runs every feature MuJoCo has."""


@dataclass(frozen=True)
class Detour:
    """Episodes of one task moved from the backend the run names to another, and why."""

    task: str
    episodes: int
    backend: str
    to: str
    reasons: Mapping[str, str]

    def message(self) -> str:
        why = "; ".join(f"{feature}: {reason}" for feature, reason in sorted(self.reasons.items()))
        return (f"{self.task}: {self.episodes} episode{'s' if self.episodes != 1 else ''} run on backend "
                f"{self.to}, not {self.backend} ({why})")


@dataclass
class Route:
    """The episodes one backend runs."""

    backend: str
    settings: dict[str, Any]
    episodes: list[PlannedEpisode] = field(default_factory=list)


class Unroutable(ValueError):
    """A plan requires features that neither the chosen backend nor the fallback can run."""


def plan_requires(item: PlannedEpisode) -> tuple[str, ...]:
    """The features the episode's plan file lists (`requires`), read without building the plan's model."""
    return tuple(json.loads(item.plan_path.read_text()).get("requires", ()))


def route(queue: Sequence[PlannedEpisode], backend: str, settings: Mapping[str, Any], *,
          fallback: str = FALLBACK, fallback_settings: Mapping[str, Any] | None = None,
          requires: Callable[[PlannedEpisode], Sequence[str]] = plan_requires) -> tuple[list[Route], list[Detour]]:
    """Split `queue` (in its order) between `backend` and `fallback`: the routes that have episodes (the chosen
    backend's first) and the detours taken, one per task."""
    main = Route(backend, dict(settings))
    other = Route(fallback, dict(fallback_settings or {}))
    detours: dict[str, Detour] = {}
    verdicts: dict[tuple[str, ...], dict[str, str]] = {}
    for item in queue:
        needs = tuple(requires(item))
        if needs not in verdicts:
            verdicts[needs] = unsupported_features(backend, needs, settings) if needs else {}
        missing = verdicts[needs]
        if not missing:
            main.episodes.append(item)
            continue
        if backend == fallback or unsupported_features(fallback, needs, other.settings):
            raise Unroutable(f"{item.task} ({item.plan_path.name}) requires "
                             + "; ".join(f"{f}: {r}" for f, r in sorted(missing.items()))
                             + (f", and backend {fallback} cannot run it either" if backend != fallback else ""))
        other.episodes.append(item)
        known = detours.get(item.task)
        detours[item.task] = Detour(item.task, (known.episodes if known else 0) + 1, backend, fallback,
                                    {**(known.reasons if known else {}), **missing})
    return [r for r in (main, other) if r.episodes], list(detours.values())
