"""Task validity: the scripted expert (the privileged `oracle`) solves a task, `zero` and `random` do not, on
a task that declares what must be remembered (`memory:`) the expert denied that history (`memoryless`,
`dojo.experts.memoryless`) does no better than chance: the task really needs memory, and on a task whose expert
fits things into tight targets the expert aiming them `--perturb-mm` off (`perturbed`, `dojo.experts.perturbed`)
fails on most seeds: the tolerances really bind.

DESIGN section 7: every built-in task ships an expert that succeeds on nearly every seed, and a zero policy
must not succeed. This module compiles (or reuses) the plans of the first N scene seeds of each task (Generalization
tasks split between the standard and random settings as in the protocol), runs a policy on them on the CPU
backend with continuous slots, and prints the table:

    python -m dojo.experts.validity --seeds 50 --jobs 16           # the full table (minutes on 16 cores)
    python -m dojo.experts.validity --tasks stack_blocks --seeds 3
    python -m dojo.experts.validity --tasks insert_tubes --seeds 20 --policies expert perturbed --perturb-mm 3

Plans are cached under `$DOJO_PLAN_CACHE/validity` (default ~/.cache/robodojo/plans/validity), named by hash.
"""

from __future__ import annotations

import argparse
import multiprocessing
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from dojo.backends.registry import BackendOptions, make_backend
from dojo.compiler.plan import Plan, plan_hash
from dojo.compiler.spec_library import SpecLibrary
from dojo.compiler.suite_compile import compile_plan_files
from dojo.compiler.taxonomy import taxonomy_of
from dojo.experts.memoryless import chance_level
from dojo.experts.perturbed import PERTURB_DISTANCE, has_fits

from dojo.evaluation.policy_link import is_privileged
from dojo.cli.run_cmd import DEFAULT_PLAN_CACHE

SUCCESS_BAR = 0.95


@dataclass(frozen=True)
class Outcome:
    task: str
    setting: str
    seed: int
    success: bool
    score: float
    steps: int


def episode_list(library: SpecLibrary, task: str, seeds: int) -> list[tuple[str, int]]:
    """(setting, scene seed) of the first `seeds` episodes: half in each setting for a dimension that compares two
    (RoboDojo's Generalization: standard and random), else all standard."""
    compared = taxonomy_of(library).compare_settings(library.get("task", task).data["dimension"])
    if not compared:
        return [("standard", i) for i in range(seeds)]
    first = (seeds + 1) // 2
    return [(compared[0], i) for i in range(first)] + [(compared[1], i) for i in range(seeds - first)]


def plan_files(library: SpecLibrary, tasks: Sequence[str], seeds: int, cache: Path, jobs: int | str = 1
               ) -> dict[str, list[Path]]:
    """Plan files of every task's validity episodes, compiling the missing ones (in `jobs` processes; `"auto"`
    as `suite_compile.worker_count` decides, so a few plans compile here rather than in processes that take seconds
    to start)."""
    out: dict[str, list[Path]] = {}
    todo = []
    for task in tasks:
        spec = library.get("task", task)
        for setting, seed in episode_list(library, task, seeds):
            digest = plan_hash(library, spec, setting, seed)
            path = cache / task / f"{setting}-{seed}-{digest[:16]}.json"
            out.setdefault(task, []).append(path)
            if not path.exists():
                todo.append((spec.id, spec.package, setting, seed, str(path)))
    compile_plan_files(library, todo, jobs=jobs)
    return out


def run_policy(model: Any, paths: Sequence[Path], num_envs: int = 8, threads: int | None = None,
               max_steps: int | None = None) -> list[Outcome]:
    """Run `model` (an XPolicyLab Model) on every plan, `num_envs` at a time. `max_steps` cuts every episode
    short after that many steps, as a failure unless it succeeded first (a quick check that a policy does not
    succeed early); the plans are run as compiled, so an outcome always names the plan that produced it."""
    plans = {path: Plan.load(path) for path in paths}
    meta = model.metadata
    queue = list(paths)
    outcomes: list[Outcome] = []
    backend = make_backend("mujoco", BackendOptions(privileged=is_privileged(meta), settings={"threads": threads},
                                                    plan_paths={p.hash: str(k) for k, p in plans.items()}))
    try:
        first = [queue.pop(0) for _ in range(min(num_envs, len(queue)))]
        backend.load([plans[p] for p in first])
        slots = dict(enumerate(first))
        obs = dict(zip(slots, backend.reset(list(slots))))
        model.reset_batch(list(slots))
        chunks: dict[int, np.ndarray] = {}
        while slots:
            need = [i for i in slots if len(chunks.get(i, ())) == 0]
            if need:
                model.update_obs_batch([obs[i] for i in need], need)
                for i, chunk in zip(need, np.asarray(model.get_action_batch(need))):
                    chunks[i] = chunk
            ids = sorted(slots)
            actions = np.stack([chunks[i][0] for i in ids])
            for i in ids:
                chunks[i] = chunks[i][1:]
            result = backend.step(actions, ids, mode=meta.action_mode)
            ended = []
            for k, i in enumerate(ids):
                obs[i] = result.obs[k]
                if result.done[k] or (max_steps is not None and result.steps[k] >= max_steps):
                    plan = plans[slots[i]]
                    outcomes.append(Outcome(plan.task, plan.setting, plan.seed, bool(result.success[k]),
                                            float(result.score[k]), int(result.steps[k])))
                    ended.append(i)
            for i in ended:
                chunks.pop(i, None)
                if queue:
                    slots[i] = queue.pop(0)
                    obs[i] = backend.reset([i], [plans[slots[i]]])[0]
                    model.reset_batch([i])
                else:
                    del slots[i]
    finally:
        backend.close()
    return outcomes


def policies(seed: int = 0, perturb: float = PERTURB_DISTANCE) -> dict[str, Any]:
    """The policies of the table: the expert, the expert denied the history (`memoryless`, for the tasks that
    declare one: `dojo.experts.memoryless`), the expert aiming its fits `perturb` metres off (`perturbed`, for the
    tasks whose expert fits something: `dojo.experts.perturbed`), zero and random."""
    from xpolicylab.policies import RandomPolicy, ZeroPolicy

    from dojo.experts.memoryless import MemorylessOracle
    from dojo.experts.oracle import OraclePolicy
    from dojo.experts.perturbed import PerturbedOracle

    return {"expert": OraclePolicy(), "memoryless": MemorylessOracle(),
            "perturbed": PerturbedOracle({"distance": perturb}), "zero": ZeroPolicy({"chunk_size": 8}),
            "random": RandomPolicy({"chunk_size": 8, "seed": seed})}


def runs(policy: str, task: Any) -> bool:
    """Whether the table runs `policy` on `task`: the memoryless expert only where the task declares `memory:`,
    the perturbed one only where its expert fits something."""
    if policy == "memoryless":
        return "memory" in task.data
    return policy != "perturbed" or has_fits(task)


def _run_episode(args: tuple[str, str, float]) -> Outcome:
    name, path, perturb = args
    plan = Plan.load(Path(path))
    return run_policy(policies(seed=plan.seed, perturb=perturb)[name], [Path(path)], num_envs=1, threads=1)[0]


def run_episodes(name: str, paths: Sequence[Path], jobs: int, perturb: float = PERTURB_DISTANCE) -> list[Outcome]:
    """Policy `name` (of `policies()`) on every plan, one episode per task of a pool of `jobs` processes: the
    experts plan in Python, one core each, so a many-core machine runs the whole table in minutes. Each
    episode runs alone in its backend (CPU episodes do not depend on their batch neighbours), and the random
    policy is seeded with the episode's scene seed, so the figures do not depend on `jobs`."""
    with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn")) as pool:  # never fork threads
        return list(pool.map(_run_episode, [(name, str(p), perturb) for p in paths]))


def summarize(outcomes: Sequence[Outcome]) -> tuple[float, float]:
    """(success rate, mean score) of some episodes."""
    if not outcomes:
        return 0.0, 0.0
    return float(np.mean([o.success for o in outcomes])), float(np.mean([o.score for o in outcomes]))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", nargs="*", help="task ids (default: every built-in evaluated task)")
    parser.add_argument("--seeds", type=int, default=50, help="scene seeds per task")
    parser.add_argument("--policies", nargs="*", default=["expert", "memoryless", "perturbed", "zero", "random"])
    parser.add_argument("--perturb-mm", type=float, default=1000 * PERTURB_DISTANCE,
                        help="how far (mm) the perturbed expert aims its fitting targets off")
    parser.add_argument("--jobs", type=int, default=1,
                        help="processes compiling plans and, above 1, running one episode each at a time")
    parser.add_argument("--num-envs", type=int, default=8, help="episodes at a time with --jobs 1")
    parser.add_argument("--cache", type=Path, default=DEFAULT_PLAN_CACHE / "validity")
    args = parser.parse_args(argv)
    library = SpecLibrary.load([])
    training_only = taxonomy_of(library).training_only
    tasks = args.tasks or sorted(s.id for s in library.of_kind("task") if s.data["dimension"] not in training_only)
    files = plan_files(library, tasks, args.seeds, args.cache, jobs=args.jobs)
    perturb = args.perturb_mm / 1000
    table = policies(perturb=perturb)
    print("| task | episodes | " + " | ".join(f"{p} success | {p} score" for p in args.policies) + " | chance |")
    print("|---|---|" + "---|---|" * len(args.policies) + "---|")
    for task in tasks:
        cells = []
        spec = library.get("task", task)
        for name in args.policies:
            if not runs(name, spec):
                cells.append("- | -")
                continue
            start = time.monotonic()
            if args.jobs > 1:
                outcomes = run_episodes(name, files[task], args.jobs, perturb)
            else:
                outcomes = run_policy(table[name], files[task], num_envs=args.num_envs)
            rate, score = summarize(outcomes)
            failed = [f"{o.setting} {o.seed}" for o in outcomes if not o.success]
            cells.append(f"{100 * rate:.0f}% | {score:.1f}")
            print(f"  {task} {name}: {100 * rate:.0f}% ({time.monotonic() - start:.0f} s)"
                  + (f"; failed: {', '.join(failed)}" if failed and rate > 0.5 else ""), flush=True)
        chance = f"{100 * chance_level(library, spec):.1f}%" if "memory" in spec.data else "-"
        print(f"| {task} | {len(files[task])} | " + " | ".join(cells) + f" | {chance} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
