"""Scores exactly as RoboDojo reports them, computed from stored episodes.

The aggregation order is the paper's (section "Simulation Benchmark Leaderboard"):

1. per task: success rate (percent of episodes that succeeded) and mean score (0-100) over the task's
   episodes; a Generalization task's 50 episodes are 25 `standard` + 25 `random`, pooled;
2. per dimension: the unweighted mean over the dimension's tasks;
3. overall: the unweighted mean of the dimension means, *not* of the tasks, so that a dimension with more
   tasks (Generalization has 12, Memory 6) does not dominate;
4. all three levels are computed separately for each seed replicate, then reported as mean and standard
   deviation over the replicates (the paper: three seeds, "mean and standard deviation").

A seed replicate is one (run id, eval seed) pair. That covers both submission styles the paper allows: one
checkpoint evaluated under three evaluation seeds (one run, three eval seeds), or three training-seed
checkpoints (three runs).

Standard deviation: the paper does not say whether it divides by n or n - 1. We use the *sample* standard
deviation (ddof = 1, Bessel's correction): the three seeds are a sample of the seeds one could have drawn, and
the number is meant to tell how much a re-run would move the score; the population formula understates that
by a factor sqrt((n-1)/n) (0.82 for three seeds). With a single replicate the std is undefined and reported
as None, never as 0.

Generalization standard vs random: per replicate the mean over Generalization tasks of each setting's
success and score; the relative drop is (standard - random) / standard of the means over replicates, as in
the paper's table (e.g. 21.98 / 1.57 -> 92.9 %), and None when the standard score is 0.

A run without any task of some dimension gets an overall over the dimensions it has, flagged `partial`
with the missing dimensions listed; such a number is not comparable with a full leaderboard entry.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from typing import Any, NamedTuple

from dojo.compiler.taxonomy import Taxonomy, builtin_taxonomy
from dojo.evaluation.episode import EpisodeResult

STD_DDOF = 1  # sample standard deviation over seed replicates; see the module docstring
STANDARD, RANDOM = "standard", "random"


class Replicate(NamedTuple):
    """One seed replicate of an evaluation."""

    run_id: str
    eval_seed: int


@dataclass(frozen=True)
class Stat:
    """A metric over seed replicates: one value per replicate, their mean and (sample) standard deviation."""

    mean: float
    std: float | None
    values: tuple[float, ...]


@dataclass(frozen=True)
class Metrics:
    """Success rate in percent (0-100) and mean score (0-100)."""

    success: Stat
    score: Stat


@dataclass(frozen=True)
class TaskScore:
    task: str
    dimension: str
    episodes: int  # over all replicates
    metrics: Metrics
    settings: dict[str, Metrics]  # per setting (`standard`, `random`, ...) the same metrics


@dataclass(frozen=True)
class DimensionScore:
    dimension: str
    tasks: tuple[str, ...]
    metrics: Metrics


@dataclass(frozen=True)
class GeneralizationSplit:
    standard: Metrics
    random: Metrics
    relative_drop_score: float | None  # fraction, e.g. 0.929
    relative_drop_success: float | None


@dataclass(frozen=True)
class Scores:
    replicates: tuple[Replicate, ...]
    tasks: tuple[TaskScore, ...]
    dimensions: dict[str, DimensionScore]  # only the dimensions present, in leaderboard order
    overall: Metrics
    missing_dimensions: tuple[str, ...]
    partial: bool
    generalization: GeneralizationSplit | None
    notes: tuple[str, ...]  # anything that makes the numbers less comparable (uneven replicates, ...)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


class ScoringError(ValueError):
    """The episodes cannot be scored (none given, or an inconsistent mix)."""


def mean(values: Sequence[float]) -> float:
    return math.fsum(values) / len(values)


def stat(values: Sequence[float]) -> Stat:
    """Mean and sample standard deviation (ddof = STD_DDOF) of per-replicate values."""
    if not values:
        raise ScoringError("cannot summarise an empty set of values")
    m = mean(values)
    std = None
    if len(values) > STD_DDOF:
        std = math.sqrt(math.fsum((v - m) ** 2 for v in values) / (len(values) - STD_DDOF))
    return Stat(mean=m, std=std, values=tuple(values))


def relative_drop(standard: float, random: float) -> float | None:
    """(standard - random) / standard, the paper's Generalization robustness measure; None if standard is 0."""
    return None if standard == 0 else (standard - random) / standard


def _episode_metrics(episodes: Sequence[EpisodeResult]) -> tuple[float, float]:
    return (100.0 * sum(e.success for e in episodes) / len(episodes), mean([e.score for e in episodes]))


def _metrics(pairs: Sequence[tuple[float, float]]) -> Metrics:
    return Metrics(success=stat([p[0] for p in pairs]), score=stat([p[1] for p in pairs]))


def score_episodes(rows: Iterable[EpisodeResult], split: str = "public", taxonomy: Taxonomy | None = None) -> Scores:
    """Score one leaderboard entry (one policy): the rows of `split`, grouped into seed replicates, by the
    scored dimensions of `taxonomy` (RoboDojo's when None)."""
    taxonomy = taxonomy or builtin_taxonomy()
    scored_dims = taxonomy.scored
    episodes = [r for r in rows if r.split == split]
    if not episodes:
        raise ScoringError(f"no {split} episodes to score")
    task_dimension: dict[str, str] = {}
    for e in episodes:
        if task_dimension.setdefault(e.task, e.dimension) != e.dimension:
            raise ScoringError(
                f"task {e.task!r} appears under two dimensions: {task_dimension[e.task]!r}, {e.dimension!r}"
            )
        if e.dimension not in scored_dims:
            raise ScoringError(f"task {e.task!r} has dimension {e.dimension!r}, which is not scored (scored: "
                               f"{', '.join(scored_dims)})")

    # replicate -> task -> episodes
    by_rep: dict[Replicate, dict[str, list[EpisodeResult]]] = defaultdict(lambda: defaultdict(list))
    for e in episodes:
        by_rep[Replicate(e.run_id, e.eval_seed)][e.task].append(e)
    replicates = tuple(sorted(by_rep))
    tasks = sorted(task_dimension, key=lambda t: (scored_dims.index(task_dimension[t]), t))
    notes: list[str] = []

    task_scores: list[TaskScore] = []
    # replicate -> dimension -> list of (success, score) per task
    per_rep_dim: dict[Replicate, dict[str, list[tuple[float, float]]]] = defaultdict(lambda: defaultdict(list))
    # replicate -> setting -> list of (success, score) per task of a dimension that compares settings
    per_rep_gen: dict[Replicate, dict[str, list[tuple[float, float]]]] = defaultdict(lambda: defaultdict(list))
    for task in tasks:
        dimension = task_dimension[task]
        pairs, setting_pairs = [], defaultdict(list)
        reps_with_task = [rep for rep in replicates if task in by_rep[rep]]
        if len(reps_with_task) != len(replicates):
            notes.append(f"task {task} was evaluated in {len(reps_with_task)} of {len(replicates)} seed replicates")
        counts = set()
        for rep in reps_with_task:
            task_episodes = by_rep[rep][task]
            counts.add(len(task_episodes))
            pair = _episode_metrics(task_episodes)
            pairs.append(pair)
            per_rep_dim[rep][dimension].append(pair)
            by_setting: dict[str, list[EpisodeResult]] = defaultdict(list)
            for e in task_episodes:
                by_setting[e.setting].append(e)
            for setting, setting_episodes in by_setting.items():
                setting_pair = _episode_metrics(setting_episodes)
                setting_pairs[setting].append(setting_pair)
                if taxonomy.compare_settings(dimension):
                    per_rep_gen[rep][setting].append(setting_pair)
        if len(counts) > 1:
            notes.append(f"task {task} has different episode counts across seed replicates: {sorted(counts)}")
        task_scores.append(TaskScore(
            task=task, dimension=dimension, episodes=sum(len(by_rep[r][task]) for r in reps_with_task),
            metrics=_metrics(pairs), settings={s: _metrics(p) for s, p in sorted(setting_pairs.items())},
        ))

    present = [d for d in scored_dims if d in task_dimension.values()]
    dimensions: dict[str, DimensionScore] = {}
    for d in present:
        reps = [rep for rep in replicates if per_rep_dim[rep].get(d)]
        dim_pairs = [(mean([p[0] for p in per_rep_dim[r][d]]), mean([p[1] for p in per_rep_dim[r][d]])) for r in reps]
        dimensions[d] = DimensionScore(
            dimension=d, tasks=tuple(t.task for t in task_scores if t.dimension == d), metrics=_metrics(dim_pairs),
        )

    overall_pairs = []
    for rep in replicates:
        rep_dims = [d for d in present if per_rep_dim[rep].get(d)]
        if len(rep_dims) != len(present):
            notes.append(f"seed replicate {rep.run_id}/{rep.eval_seed} lacks dimensions "
                         f"{[d for d in present if d not in rep_dims]}; its overall averages the others")
        dim_means = [(mean([p[0] for p in per_rep_dim[rep][d]]), mean([p[1] for p in per_rep_dim[rep][d]]))
                     for d in rep_dims]
        overall_pairs.append((mean([p[0] for p in dim_means]), mean([p[1] for p in dim_means])))

    missing = tuple(d for d in scored_dims if d not in present)
    return Scores(
        replicates=replicates,
        tasks=tuple(task_scores),
        dimensions=dimensions,
        overall=_metrics(overall_pairs),
        missing_dimensions=missing,
        partial=bool(missing),
        generalization=_generalization_split(per_rep_gen, replicates),
        notes=tuple(notes),
    )


def report_dimensions(report: dict[str, Any]) -> dict[str, str]:
    """Scored dimension id -> label, in order, of a report (`build_report` writes them; RoboDojo's otherwise)."""
    listed = report.get("dimensions")
    if listed:
        return {d["id"]: d["label"] for d in listed}
    taxonomy = builtin_taxonomy()
    return {d: taxonomy.label(d) for d in taxonomy.scored}


def _generalization_split(
    per_rep_gen: dict[Replicate, dict[str, list[tuple[float, float]]]], replicates: tuple[Replicate, ...]
) -> GeneralizationSplit | None:
    """Standard vs random over the Generalization tasks, or None if a run lacks either setting."""
    reps = [r for r in replicates if per_rep_gen[r].get(STANDARD) and per_rep_gen[r].get(RANDOM)]
    if not reps:
        return None

    def setting_metrics(setting: str) -> Metrics:
        return _metrics([
            (mean([p[0] for p in per_rep_gen[r][setting]]), mean([p[1] for p in per_rep_gen[r][setting]]))
            for r in reps
        ])

    standard, random = setting_metrics(STANDARD), setting_metrics(RANDOM)
    return GeneralizationSplit(
        standard=standard,
        random=random,
        relative_drop_score=relative_drop(standard.score.mean, random.score.mean),
        relative_drop_success=relative_drop(standard.success.mean, random.success.mean),
    )
