"""`dojo run`: compile (or reuse) a suite's plans, evaluate a policy on them, print the scores.

With no arguments it runs the built-in default suite with the built-in reference policy on the CPU backend.
Results go to `results.sqlite` in the run's output folder, which Hydra names after the suite, the policy and the
overrides, so re-running the same command resumes the same run. `record=head|all` films every episode into the
output folder's `videos/` (and saves its trajectory under `trajectories/`); the report links the videos.
"""

from __future__ import annotations

import json
import os
import sys
from functools import partial
from pathlib import Path
from collections.abc import Callable
from typing import Any

from omegaconf import DictConfig, OmegaConf
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from dojo.backends.base import Backend
from dojo.backends.mujoco.render import ensure_headless_gl
from dojo.backends.registry import check_settings, factory_from_config

from dojo.evaluation.camera_budget import budget_message, image_size, images_per_second
from dojo.compiler.episodes import PlannedEpisode
from dojo.evaluation.episode import EpisodeKey, episode_key
from dojo.evaluation.evaluate import evaluate, run_id_for
from dojo.evaluation.policy_link import (PRIVILEGED_NOTE, device_rule_for, is_privileged, policy_config_for,
                                         policy_identity)
from dojo.evaluation.recorder import EpisodeRecorder, record_cameras
from dojo.evaluation.side_by_side import SharedProgress, run_in_process, run_side_by_side

DEFAULT_PLAN_CACHE = Path(os.environ.get("DOJO_PLAN_CACHE", Path.home() / ".cache" / "robodojo" / "plans"))


def _hidden_seeds(cfg: DictConfig, suite: Any) -> list[int] | None:
    """The private seed set a suite names, from the evaluator's secrets file (never from the spec package)."""
    verification = suite.data.get("verification")
    if not verification or not cfg.hidden_seeds:
        return None
    secrets = json.loads(Path(cfg.hidden_seeds).read_text())
    if verification["seed_set"] not in secrets:
        raise KeyError(f"{cfg.hidden_seeds} has no seed set '{verification['seed_set']}'")
    return [int(s) for s in secrets[verification["seed_set"]]]


def _backend_factory(backend: dict[str, Any], metadata: Any, cameras: tuple[str, ...], size: tuple[int, int],
                     plan_paths: dict[str, str] | None = None) -> Callable[[], Backend]:
    """The backend `backend` names (the `backend=<name>` config group's content, or the fallback a route chose),
    rendering `cameras` (the policy's plus those being recorded, and no others) at `size`. Only a policy whose
    metadata says `extra.privileged` (the oracle) gets the simulator state in its observations. The backend is
    told the policy's action mode, so that a compiling backend builds no other (mjx: no IK for joint actions)."""
    return factory_from_config(backend, cameras=cameras, width=size[0], height=size[1],
                               privileged=is_privileged(metadata), plan_paths=plan_paths,
                               action_modes=(metadata.action_mode,))


def _routes(cfg: DictConfig, queue: list[PlannedEpisode], quiet: bool) -> list[tuple[dict[str, Any], list[Any]]]:
    """The run's episodes by the backend that runs them (`dojo.evaluation.routing`), each detour printed; the
    chosen backend's settings checked first (`check_settings`), so that a bad one stops the run before it starts."""
    from dojo.evaluation.routing import route

    chosen = OmegaConf.to_container(cfg.backend, resolve=True)
    name = str(chosen.pop("name"))  # type: ignore[union-attr]
    check_settings(name, chosen)  # type: ignore[arg-type]
    routes, detours = route(queue, name, chosen)  # type: ignore[arg-type]
    for detour in detours:
        Console(stderr=True, soft_wrap=True).print(f"[yellow]backend:[/yellow] {escape(detour.message())}",
                                                   highlight=False)
    if detours and quiet:
        for detour in detours:
            print(json.dumps({"detour": detour.message()}), flush=True)
    return [({"name": r.backend, **r.settings}, r.episodes) for r in routes]


def run_task(cfg: DictConfig) -> int:
    """The `dojo run` job."""
    ensure_headless_gl()
    from hydra.core.hydra_config import HydraConfig

    from dojo.compiler.plan import Plan
    from dojo.compiler.horizon import horizons_file, load_demo_lengths
    from dojo.compiler.spec_library import SpecLibrary
    from dojo.compiler.suite_compile import compile_suite
    from dojo.compiler.taxonomy import taxonomy_of

    from dojo.evaluation.policy_link import open_policy
    from dojo.evaluation.progress import Progress
    from dojo.report.make_report import write_report
    from dojo.evaluation.results_store import ResultsStore
    from dojo.report.scoring import score_episodes

    library = SpecLibrary.load([Path(p) for p in cfg.packs])
    suite = library.get("suite", cfg.suite.id)
    seeds = list(cfg.seeds) if cfg.seeds is not None else None
    plan_dir = Path(cfg.plans) if cfg.plans else DEFAULT_PLAN_CACHE / suite.id
    tasks = list(cfg.tasks) if cfg.tasks is not None else None
    demos = load_demo_lengths(horizons_file(cfg.horizons))
    stats = compile_suite(library, suite, plan_dir, jobs=cfg.jobs, seeds=seeds, episodes=cfg.episodes,
                          demo_lengths=demos, tasks=tasks)
    _say_compiled(stats, suite.id)
    queue = list(stats.episodes)
    hidden = _hidden_seeds(cfg, suite)
    if hidden:
        hidden_dir = plan_dir.with_name(plan_dir.name + "-hidden")
        count = suite.data["verification"].get("episodes", 10)
        hidden_stats = compile_suite(library, suite, hidden_dir, jobs=cfg.jobs, seeds=hidden, episodes=count,
                                     demo_lengths=demos, tasks=tasks, split="hidden")
        _say_compiled(hidden_stats, f"{suite.id} (hidden layouts)")
        queue += hidden_stats.episodes

    embodiment = library.get("task", queue[0].task).data["embodiment"] if queue else "arx_x5_bimanual"
    policy_cfg = OmegaConf.to_container(cfg.policy, resolve=True)
    if isinstance(policy_cfg.get("url"), list) and len(policy_cfg["url"]) > 1 and cfg.launcher.name != "ray":
        raise ValueError(f"policy.url lists {len(policy_cfg['url'])} servers, one per worker of launcher=ray; "
                         "launcher=local talks to one")
    policy = open_policy(policy_config_for(policy_cfg, 0), embodiment)  # type: ignore[arg-type]
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    store_path = Path(cfg.results) if cfg.results else out_dir / "results.sqlite"
    robot_cameras = Plan.load(queue[0].plan_path).cameras if queue and cfg.record != "none" else []
    recorded = record_cameras(str(cfg.record), robot_cameras) if robot_cameras else ()
    on_device = policy_cfg.get("on_device", "off")
    try:  # a plan no backend runs, or policy.on_device=on where it cannot be, stops the run here
        routes = _routes(cfg, queue, quiet=cfg.progress == "jsonl")
        changed = _rule_changes_results(policy, routes, bool(recorded), on_device)
        side_by_side = routes_side_by_side(cfg.routes)
    except BaseException:
        policy.close()
        raise
    identity = {"suite": suite.id, "policy": policy.metadata.name, "policy_config": policy_identity(policy_cfg),
                "backend": cfg.backend.name, "seeds": seeds, "episodes": cfg.episodes, "hidden": bool(hidden)}
    if tasks is not None:  # only when set: the ids of runs of whole suites stay as they were
        identity["tasks"] = sorted(tasks)
    if changed:
        identity["policy_on_device"] = True
    run_id = run_id_for(identity)
    meta = policy.metadata
    cameras = tuple(meta.cameras) + tuple(c for c in recorded if c not in meta.cameras)
    width, height, size_warning = image_size(meta, cfg.width, cfg.height)
    action_mode = meta.action_mode  # not the policy link itself: a Ray worker gets a copy of this factory
    recorder_factory = (partial(EpisodeRecorder, out_dir, recorded, action_mode=action_mode,
                                relative_to=store_path.parent) if recorded else None)  # pickles: a route's process
    try:
        with ResultsStore(store_path) as store:
            store.ensure_run(run_id, identity)
            finished = store.rows(run_id)
            done = store.finished(run_id)
            left = routes_left(routes, done)
            if cfg.progress != "quiet":
                _say_what_is_rendered(meta, cameras, (width, height), size_warning, queue, done,
                                      timed_here=str(cfg.backend.name) == "mujoco")
            with Progress(len(queue), mode=str(cfg.progress), finished=finished) as progress:
                timeout = float(cfg.episode_timeout_s) if cfg.episode_timeout_s else None
                if cfg.launcher.name == "ray":
                    for backend, episodes in routes:
                        plan_paths = {item.plan_hash: str(item.plan_path) for item in episodes}
                        _evaluate_on_ray(cfg, backend, episodes, policy_cfg, embodiment, run_id, store, progress,
                                         plan_paths, timeout, (meta, cameras, (width, height)), recorder_factory)
                else:
                    common = dict(run_id=run_id, num_envs=int(cfg.num_envs), timeout=timeout,
                                  rendering=(meta, cameras, (width, height)), recorder_factory=recorder_factory,
                                  on_device=on_device)
                    if side_by_side and len(left) > 1:
                        shared = SharedProgress(progress)
                        first, *others = left
                        run_side_by_side(
                            [partial(_evaluate_route, routes, first, policy=policy, store=store, progress=shared,
                                     **common)]
                            + [partial(run_in_process, partial(_evaluate_route_apart, routes, k, policy_cfg=policy_cfg,
                                                               embodiment=embodiment, store_path=store_path, **common),
                                       shared)
                               for k in others])
                    else:
                        for k in left:
                            _evaluate_route(routes, k, None, policy=policy, store=store, progress=progress, **common)
            rows = store.rows(run_id)
    finally:
        policy.close()
    public = [r for r in rows if r.split == "public"]
    taxonomy = taxonomy_of(library)
    _print_scores(score_episodes(public, taxonomy=taxonomy), run_id, store_path, quiet=cfg.progress == "jsonl",
                  privileged=is_privileged(meta))
    if cfg.report:
        report_path = Path(cfg.report)
        write_report([store_path], report_path, report_path.with_suffix(".html"), run_ids={run_id}, taxonomy=taxonomy)
        print(f"report: {report_path} and {report_path.with_suffix('.html')}")
    return 0


def _say_compiled(stats: Any, label: str) -> None:
    """On stderr, where plans were compiled for the run (`CompileStats.summary`), and why a folder's plans were
    compiled again (`compiler_note`): a run that only reuses plans says nothing, and one that compiles waits for
    it, so the wait gets its reason (a folder compiled elsewhere, by another install, was compiled again silently)."""
    if not stats.compiled:
        return
    print(stats.summary(label), file=sys.stderr, flush=True)
    if note := stats.compiler_note():
        print(note, file=sys.stderr, flush=True)


ROUTES = ("side_by_side", "in_turn")
"""`routes`: the episodes of the chosen backend and of its fallback at the same time, or one backend's after the
other's (`dojo.evaluation.side_by_side`)."""


def routes_side_by_side(value: Any) -> bool:
    """Whether `routes` (one of `ROUTES`) runs a run's routes at the same time."""
    if value not in ROUTES:
        raise ValueError(f"routes must be one of {', '.join(ROUTES)}, got {value!r}")
    return value == "side_by_side"


def routes_left(routes: list[tuple[dict[str, Any], list[Any]]], finished: set[EpisodeKey]) -> list[int]:
    """The routes, by index, that still have an episode not in `finished` (the store's keys): a resumed run starts
    no backend, and spawns no process, for a route whose episodes are all recorded."""
    return [k for k, (_, episodes) in enumerate(routes)
            if any(episode_key(item) not in finished for item in episodes)]


def _evaluate_route(routes: list[tuple[dict[str, Any], list[Any]]], k: int, stop: Any, *, policy: Any, store: Any,
                    run_id: str, num_envs: int, rendering: tuple[Any, tuple[str, ...], tuple[int, int]],
                    progress: Any, timeout: float | None, recorder_factory: Any, on_device: Any) -> int:
    """`evaluate` on route `k` in this process, with the policy link `policy` and the results store `store`; the
    route's environments are known to the policy by ids of its own (`k * num_envs` on), so that routes may share
    one policy server."""
    backend, episodes = routes[k]
    plan_paths = {item.plan_hash: str(item.plan_path) for item in episodes}
    return evaluate(episodes, _backend_factory(backend, *rendering, plan_paths), policy, store, run_id,
                    num_envs=num_envs, progress=progress, episode_timeout_s=timeout,
                    recorder_factory=recorder_factory, on_device=on_device, env_id_base=k * num_envs, stop=stop)


def _evaluate_route_apart(routes: list[tuple[dict[str, Any], list[Any]]], k: int, stop: Any, *,
                          policy_cfg: dict[str, Any], embodiment: str, store_path: Path, **shared: Any) -> int:
    """`_evaluate_route` in a process of its own (`side_by_side`), with a policy link and a results-store connection
    of its own, as a launcher's worker has."""
    from dojo.evaluation.policy_link import open_policy
    from dojo.evaluation.results_store import ResultsStore

    link = open_policy(policy_config_for(policy_cfg, k), embodiment)
    try:
        with ResultsStore(store_path) as store:
            return _evaluate_route(routes, k, stop, policy=link, store=store, **shared)
    finally:
        link.close()


def _rule_changes_results(policy: Any, routes: list[tuple[dict[str, Any], list[Any]]], recording: bool,
                          on_device: Any) -> bool:
    """Whether the policy's rule runs inside a backend's step for some of the run's episodes and gives other
    numbers there than on the host (`random`: JAX's generator, not numpy's). Such a run is another run than the
    same command on the host path, so its identity says so; `zero`'s rule gives the host's numbers bit for bit,
    so where it runs stays out of the identity, and `policy.on_device=on` fails here, before anything runs, when
    a backend of the run cannot run the rule."""
    rules = [device_rule_for(policy, str(backend["name"]), recording=recording, on_device=on_device)
             for backend, _ in routes]
    return any(rule is not None and not rule.matches_host for rule in rules)


def _evaluate_on_ray(cfg: DictConfig, backend: dict[str, Any], queue: list[PlannedEpisode], policy_cfg: dict[str, Any],
                     embodiment: str, run_id: str, store: Any, progress: Any, plan_paths: dict[str, str],
                     timeout: float | None, rendering: tuple[Any, tuple[str, ...], tuple[int, int]],
                     recorder_factory: Any) -> int:
    """`launcher=ray`: the episodes over the workers of a Ray cluster (dojo.launch.ray_launcher), each building
    `backend` as this process would (with its own share of threads) and opening its own policy link."""
    from dojo.launch.ray_launcher import RayOptions, WorkerJob, evaluate_on_ray

    options = RayOptions.of(OmegaConf.to_container(cfg.launcher, resolve=True), str(backend["name"]))
    settings = options.backend_settings(backend)
    job = WorkerJob(run_id=run_id, backend_for=partial(_backend_factory, settings, *rendering), policy=policy_cfg,
                    embodiment=embodiment, num_envs=int(cfg.num_envs), plan_paths=plan_paths,
                    episode_timeout_s=timeout, recorder_factory=recorder_factory)
    return evaluate_on_ray(queue, job, store, progress, options)


def _say_what_is_rendered(meta: Any, cameras: tuple[str, ...], size: tuple[int, int], warning: str | None,
                          queue: list[PlannedEpisode], finished: set[EpisodeKey], timed_here: bool) -> None:
    """Before a run that renders cameras: which, at what size, and the most it can cost (camera_budget); with
    `timed_here` (the mujoco backend, which renders with MuJoCo's OpenGL renderer on this machine) also how long,
    timed here. The mjx backend renders on the device, where OpenGL may not even be installed."""
    console = Console(stderr=True, soft_wrap=True)  # one line each, whatever the terminal's width
    if warning:
        console.print(f"[yellow]{escape(warning)}[/yellow]")
    todo = [q for q in queue if episode_key(q) not in finished]
    if not cameras or not todo:
        return
    from dojo.compiler.plan import Plan

    plans: dict[str, Any] = {}
    for item in todo:  # one plan per task: the horizon is the task's
        if item.task not in plans:
            plans[item.task] = Plan.load(item.plan_path)
    rate = images_per_second(plans[todo[0].task], cameras, *size) if timed_here else None
    console.print(escape(budget_message(meta, cameras, *size, [plans[q.task].horizon for q in todo], rate)),
                  highlight=False)


def _print_scores(scores: Any, run_id: str, store_path: Path, quiet: bool, privileged: bool = False) -> None:
    """The leaderboard view of one run: per task, per dimension, and overall (mean over dimensions). A privileged
    policy's table says that it is a reference, not a score to compare with."""
    if quiet:
        print(json.dumps({"run_id": run_id, "results": str(store_path), "scores": scores.to_dict(),
                          "privileged": privileged}, default=str))
        return

    def fmt(stat: Any) -> str:
        return f"{stat.mean:.1f}" + (f" ± {stat.std:.1f}" if stat.std is not None else "")

    table = Table(title=escape(f"run {run_id}" + (" (privileged reference)" if privileged else "")))
    for column in ("task", "dimension", "episodes", "success %", "score"):
        table.add_column(column, justify="left" if column in ("task", "dimension") else "right")
    for task in scores.tasks:  # names come from specs (third-party packs too): never read them as markup
        table.add_row(escape(task.task), task.dimension, str(task.episodes), fmt(task.metrics.success),
                      fmt(task.metrics.score))
    table.add_section()
    for name, dim in scores.dimensions.items():
        table.add_row(f"[bold]{name}", f"{len(dim.tasks)} tasks", "", fmt(dim.metrics.success),
                      fmt(dim.metrics.score))
    table.add_section()
    label = "overall (partial)" if scores.partial else "overall"
    table.add_row(f"[bold]{label}", "mean of dimensions", "", fmt(scores.overall.success), fmt(scores.overall.score))
    console = Console()
    console.print(table)
    if privileged:  # one unwrapped line, so that it reads (and greps) the same at any terminal width
        print(f"{PRIVILEGED_NOTE}: these are the tasks' scripted experts, showing that the tasks are solvable; "
              "evaluate a policy with policy=remote policy.url=ws://HOST:PORT", flush=True)
    console.print(f"results: {store_path}", markup=False, soft_wrap=True)
