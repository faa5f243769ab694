"""Do two backends agree on a policy's outcomes? The scripted-rollout half of `mujoco`/`mjx` parity.

State parity (`dojo.backends.mjx.parity`) compares trajectories step by step under fixed controls; what a
researcher needs besides is that a *closed-loop* evaluation scores the same on both backends. Run the same suite,
seeds and policy (normally the scripted `oracle`) once per backend, then compare the two results stores episode by
episode (same plan, evaluation seed and episode index):

    dojo run backend=mujoco results=cpu.sqlite ...
    dojo run backend=mjx    results=mjx.sqlite ...
    python -m dojo.bench.backend_agreement cpu.sqlite mjx.sqlite

It prints one row per task (episodes in both, success agreement, mean absolute score difference) and the overall
agreement, and exits 1 when the success agreement is below `--min-agreement` (98% by default, the bar of the
backends issue) or when the stores share no episode.
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from dojo.evaluation.episode import EpisodeKey, EpisodeResult
from dojo.evaluation.results_store import ResultsStore, resolve_store_path

MIN_AGREEMENT = 0.98


@dataclass(frozen=True)
class TaskAgreement:
    """Agreement of two runs on one task's shared episodes."""

    task: str
    episodes: int
    same_success: int
    success_a: int
    success_b: int
    mean_abs_score_diff: float

    @property
    def agreement(self) -> float:
        return self.same_success / self.episodes if self.episodes else 0.0


def _public(path: Path, run_id: str | None) -> dict[EpisodeKey, EpisodeResult]:
    with ResultsStore(path, readonly=True) as store:
        return {row.key: row for row in store.rows(run_id) if row.split == "public"}


def compare(a: dict[EpisodeKey, EpisodeResult], b: dict[EpisodeKey, EpisodeResult]) -> list[TaskAgreement]:
    """Per task, over the episodes both runs finished (sorted by task)."""
    by_task: dict[str, list[tuple[EpisodeResult, EpisodeResult]]] = defaultdict(list)
    for key in a.keys() & b.keys():
        by_task[a[key].task].append((a[key], b[key]))
    return [TaskAgreement(task, len(pairs), sum(x.success == y.success for x, y in pairs),
                          sum(x.success for x, _ in pairs), sum(y.success for _, y in pairs),
                          sum(abs(x.score - y.score) for x, y in pairs) / len(pairs))
            for task, pairs in sorted(by_task.items())]


def overall(rows: Sequence[TaskAgreement]) -> float:
    """Success agreement over every shared episode (episodes weigh equally, whatever their task)."""
    episodes = sum(r.episodes for r in rows)
    return sum(r.same_success for r in rows) / episodes if episodes else 0.0


def format_table(rows: Sequence[TaskAgreement], names: tuple[str, str]) -> str:
    head = f"{'task':<28} {'episodes':>8} {'agree %':>8} {names[0] + ' ok':>12} {names[1] + ' ok':>12} {'|dscore|':>9}"
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r.task:<28} {r.episodes:>8} {100 * r.agreement:>8.1f} {r.success_a:>12} {r.success_b:>12} "
                     f"{r.mean_abs_score_diff:>9.2f}")
    lines.append(f"{'overall':<28} {sum(r.episodes for r in rows):>8} {100 * overall(rows):>8.1f}")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("a", help="results store (or run folder) of the first backend")
    parser.add_argument("b", help="results store (or run folder) of the second backend")
    parser.add_argument("--run-a", default=None, help="run id in the first store (default: every run)")
    parser.add_argument("--run-b", default=None, help="run id in the second store (default: every run)")
    parser.add_argument("--min-agreement", type=float, default=MIN_AGREEMENT)
    args = parser.parse_args(argv)
    paths = (resolve_store_path(args.a), resolve_store_path(args.b))
    rows = compare(_public(paths[0], args.run_a), _public(paths[1], args.run_b))
    print(format_table(rows, (paths[0].stem, paths[1].stem)))
    if not rows:
        print("the two stores share no episode (same suite, seeds and episodes on both backends?)", file=sys.stderr)
        return 1
    if overall(rows) < args.min_agreement:
        print(f"success agreement {100 * overall(rows):.1f}% is below {100 * args.min_agreement:.0f}%", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
