"""`dojo run launcher=ray`: one run's episodes over the workers of a Ray cluster, into one results store.

Why Ray: it is what labs already operate for this (a laptop, a node with eight GPUs, a cluster of them), so we
write no scheduler, no transport and no failure detector of our own. The driver (the `dojo run` process) starts a
local cluster, or joins one (`launcher.address`), keeps the run's queue in a dispatcher actor on its own node
(`dispatch.EpisodeDispatcher`), and starts `launcher.workers` actors, each with its own backend (CPUs for
`mujoco`; `launcher.gpus_per_worker`, one by default, for `mjx`) and its own policy link (the run's server, or the
worker's own when `policy.url` lists one per worker). A worker runs the ordinary evaluation loop (`evaluate`) on
episodes it pulls as its slots free up and reports each row as its episode ends; the driver drains the rows a few
times a second, writes them to the store (the single source of truth, as in a local run) and feeds the progress
display, which therefore counts the whole cluster.

Failures: a worker that dies (its process killed, its node lost) has the episodes it pulled and did not report
put back in the queue, for the others; the run goes on. An error raised *by* a worker (its policy server
refused, say) stops the run as it would stop a local one: everything reported is stored, and the same command
resumes the rest, with either launcher (the run id does not depend on the launcher).

Plans travel with the work: a worker on a machine that cannot read the driver's plan files gets them through
Ray's object store and keeps them in its own plan cache (plans are content-addressed, so any copy will do).
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dojo.launch.dispatch import EpisodeDispatcher, episode_key, longest_first

if TYPE_CHECKING:  # the worker process imports these only once its GL platform is chosen
    from dojo.backends.base import Backend

    from dojo.evaluation.episode import EpisodeKey, EpisodeResult
    from dojo.compiler.episodes import PlannedEpisode
    from dojo.evaluation.evaluate import ProgressSink, RowSink
    from dojo.evaluation.recorder import SlotRecorder

log = logging.getLogger(__name__)

POLL_S = 0.2
"""How often the driver drains finished rows: episodes take seconds, so this adds no measurable delay."""
FINISH_S = 5.0
"""When every episode is stored, how long a worker whose `run` has not returned gets to end; one that does not was
never placed (more workers asked for than the cluster holds) and is not waited for."""
COUNT_EVERY_S = 1.0
"""How often a worker sends its count of environment steps between reports (the display's rate)."""
SHIPPED_PLANS = "shipped"
"""Sub-folder of a worker's plan cache for plans it received from the driver."""


@dataclass(frozen=True)
class RayOptions:
    """The `launcher` config group with `name: ray` (dojo/cli/config/launcher/ray.yaml)."""

    address: str | None = None
    workers: int | None = None
    cpus_per_worker: float = 1.0
    gpus_per_worker: float = 0.0
    num_cpus: int | None = None

    @classmethod
    def of(cls, launcher: Mapping[str, Any], backend: str) -> RayOptions:
        """From the launcher config; `gpus_per_worker: null` is one GPU per worker for `mjx`, none otherwise."""
        gpus = launcher.get("gpus_per_worker")
        return cls(address=launcher.get("address") or None, workers=launcher.get("workers") or None,
                   cpus_per_worker=float(launcher.get("cpus_per_worker") or 1),
                   gpus_per_worker=float(gpus if gpus is not None else (1 if backend == "mjx" else 0)),
                   num_cpus=launcher.get("num_cpus") or None)

    def backend_settings(self, backend: Mapping[str, Any]) -> dict[str, Any]:
        """A worker's backend config: `threads: 0` (one per core) becomes one per CPU the worker was given, since
        in a worker the machine's core count is shared by every worker on it."""
        settings = dict(backend)
        if "threads" in settings and not settings["threads"]:
            settings["threads"] = max(1, int(self.cpus_per_worker))
        return settings


@dataclass(frozen=True)
class WorkerJob:
    """Everything a worker needs to run the run's episodes, sent once to each worker (so: picklable)."""

    run_id: str
    backend_for: Callable[[dict[str, str]], Callable[[], Backend]]
    """Plan hash -> plan file as the worker sees it, to the backend factory of the evaluation loop."""
    policy: dict[str, Any]
    """The run's policy config; `url` may list one server per worker (`policy_config_for`)."""
    embodiment: str
    num_envs: int
    plan_paths: dict[str, str]
    """Plan hash -> plan file on the driver's machine."""
    episode_timeout_s: float | None = None
    recorder_factory: Callable[[], SlotRecorder] | None = None


def evaluate_on_ray(queue: list[PlannedEpisode], job: WorkerJob, store: RowSink, progress: ProgressSink,
                    options: RayOptions) -> int:
    """Run every queued episode not yet in `store` for the job's run on a Ray cluster; return how many ran.

    Joins `options.address`, or starts a local cluster (and stops it at the end) when there is none."""
    finished = store.finished(job.run_id)
    todo = [item for item in queue if episode_key(item) not in finished]
    if not todo:
        return 0
    import ray

    started = not ray.is_initialized()
    if started and options.address:
        ray.init(address=options.address, logging_level=logging.WARNING)
    elif started:
        start_local_cluster(options.num_cpus)
    try:
        return _drive(todo, job, store, progress, options)
    finally:
        if started:
            ray.shutdown()


def start_local_cluster(num_cpus: int | None = None) -> None:
    """A Ray cluster of this machine for this process (`num_cpus`: None = every core). Its workers run at the
    priority of `dojo run` itself: Ray's default niceness for workers, 15, makes them yield to every other process,
    and on a shared machine the others then took most of their CPU (RAY_worker_niceness, if set, is kept)."""
    import ray

    os.environ.setdefault("RAY_worker_niceness", "0")
    ray.init(num_cpus=num_cpus, include_dashboard=False, logging_level=logging.WARNING)


def _drive(todo: list[PlannedEpisode], job: WorkerJob, store: RowSink, progress: ProgressSink,
           options: RayOptions) -> int:
    """The driver's loop: start the dispatcher and the workers, write what they report, re-queue the dead's."""
    import ray
    from ray.exceptions import RayActorError
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    env = {"worker_process_setup_hook": f"{__name__}.setup_worker_process"}
    blobs = {h: Path(p).read_bytes() for h, p in job.plan_paths.items()}
    plans = [ray.put(blobs)]  # nested in a list: a worker fetches them only if it cannot read the driver's files
    horizons = {h: int(json.loads(blob)["horizon"]) for h, blob in blobs.items()}
    here = NodeAffinitySchedulingStrategy(ray.get_runtime_context().get_node_id(), soft=False)
    dispatcher = ray.remote(EpisodeDispatcher).options(num_cpus=0, scheduling_strategy=here,
                                                       runtime_env=env).remote(longest_first(todo, horizons))
    count = worker_count(options, ray.cluster_resources(), len(todo))
    log.info("ray: %d workers (%g CPU, %g GPU each) on a cluster of %s", count, options.cpus_per_worker,
             options.gpus_per_worker, _resources(ray.cluster_resources()))
    worker_class = ray.remote(_ShardWorker).options(num_cpus=options.cpus_per_worker,
                                                    num_gpus=options.gpus_per_worker, runtime_env=env)
    workers = [worker_class.remote(i, job, dispatcher, plans) for i in range(count)]
    running = {w.run.remote(): i for i, w in enumerate(workers)}
    idle: set[int] = set()
    dead: set[int] = set()
    unplaced: set[int] = set()
    written = 0
    try:
        while True:
            ready, _ = ray.wait(list(running), num_returns=len(running), timeout=POLL_S) if running else ([], [])
            failure: BaseException | None = None
            for ref in ready:
                index = running.pop(ref)
                try:
                    ray.get(ref)
                    idle.add(index)
                except RayActorError as err:
                    dead.add(index)
                    lost = ray.get(dispatcher.requeue.remote(index))
                    log.warning("ray: worker %d died (%s); %d unfinished episodes re-queued to the others",
                                index, str(err).splitlines()[0], lost)
                except Exception as err:  # noqa: BLE001 - raised by the worker's own code: stop, as a local run would
                    failure = err
            drained = ray.get(dispatcher.drain.remote())
            if drained.rows:
                store.add_many(drained.rows)
                for row in drained.rows:
                    progress.episode_finished(row)
                written += len(drained.rows)
            progress.interactions(drained.interactions)
            if failure is not None:
                raise failure
            if drained.left == 0:  # every episode stored: a worker whose run does not end now was never placed
                ended, _ = ray.wait(list(running), num_returns=len(running), timeout=FINISH_S) if running else ([], [])
                unplaced = {i for ref, i in running.items() if ref not in ended}
                return written
            if drained.queued and idle:  # episodes re-queued after the idle workers had run out of work
                running.update({workers[i].run.remote(): i for i in idle})
                idle.clear()
            if not running:
                raise RuntimeError(f"every Ray worker died with {drained.left} episodes left; the finished ones "
                                   "are stored: run the same command again to resume")
    finally:
        _stop(ray, workers, dead | unplaced, dispatcher)


def _stop(ray: Any, workers: list[Any], skip: set[int], dispatcher: Any) -> None:
    """Close the policy links of the workers not in `skip` (dead, or never placed by the cluster, whose `close`
    would wait for resources too), then end every actor of the run."""
    try:
        ray.get([w.close.remote() for i, w in enumerate(workers) if i not in skip], timeout=30)
    except Exception as err:  # noqa: BLE001 - ending the run anyway; the actors are killed below
        log.warning("ray: closing the workers: %s", str(err).splitlines()[0])
    for actor in [*workers, dispatcher]:
        ray.kill(actor)


def worker_count(options: RayOptions, cluster: Mapping[str, float], episodes: int) -> int:
    """`launcher.workers`, else as many workers as the cluster's resources hold at once; never more than episodes.

    Ray keeps a worker the cluster cannot hold waiting for resources, forever on a fixed cluster: with no
    `launcher.workers` that is an error here; an explicit count larger than what fits only warns (an autoscaling
    cluster grows for it), and the run ends when its episodes are done, whether or not every worker started."""
    held = [cluster.get(kind, 0.0) // need for kind, need in
            (("CPU", options.cpus_per_worker), ("GPU", options.gpus_per_worker)) if need]
    fits = int(min(held)) if held else episodes
    if options.workers and options.workers > fits:
        log.warning("ray: %d workers asked for, %d fit in a cluster of %s; the others start if it grows",
                    options.workers, fits, _resources(cluster))
    elif not options.workers and fits < 1:
        raise ValueError(f"a worker needs {options.cpus_per_worker:g} CPU and {options.gpus_per_worker:g} GPU "
                         f"(launcher.cpus_per_worker, launcher.gpus_per_worker) and the cluster has "
                         f"{_resources(cluster)}")
    return max(1, min(options.workers or fits, episodes))


def _resources(total: Mapping[str, float]) -> str:
    return ", ".join(f"{total[k]:g} {k}" for k in ("CPU", "GPU") if total.get(k)) or "no CPU or GPU"


def setup_worker_process() -> None:
    """Every worker process, before anything imports MuJoCo: the headless GL platform of *its* machine."""
    from dojo.backends.mujoco.render import ensure_headless_gl

    ensure_headless_gl()


def local_plan_paths(paths: Mapping[str, str], fetch: Callable[[], Mapping[str, bytes]], cache: Path) -> dict[str, str]:
    """Plan hash -> a plan file this machine can read: the driver's own file where it is visible here (one
    machine, a shared file system), else a copy from `fetch()` (the driver's plans, read once) under `cache`."""
    missing = [h for h, p in paths.items() if not Path(p).is_file()]
    local = dict(paths)
    if not missing:
        return local
    blobs = fetch()
    for digest in missing:
        target = cache / f"{digest}.json"
        if not target.is_file():  # several workers of one machine may write it: each writes whole, then renames
            target.parent.mkdir(parents=True, exist_ok=True)
            tmp = target.with_name(f"{target.name}.{os.getpid()}.tmp")
            tmp.write_bytes(blobs[digest])
            tmp.replace(target)
        local[digest] = str(target)
    return local


class _ShardWorker:
    """One Ray worker: its own backend and policy link, running `evaluate` on episodes pulled from the dispatcher.

    It is the loop's store and progress display too: rows go to the dispatcher as each episode ends (the call
    returns once the dispatcher has them), steps are counted and sent about once a second."""

    def __init__(self, index: int, job: WorkerJob, dispatcher: Any, plans: list[Any]) -> None:
        self.index, self.job, self.dispatcher, self._plans = index, job, dispatcher, plans
        self._policy: Any = None
        self._paths: dict[str, str] = {}
        self._steps = 0
        self._sent = time.monotonic()

    def run(self) -> int:
        """Evaluate until the dispatcher has nothing left for this worker; return how many episodes ran."""
        import ray

        from dojo.evaluation.evaluate import evaluate
        from dojo.evaluation.policy_link import open_policy, policy_config_for
        from dojo.cli.run_cmd import DEFAULT_PLAN_CACHE

        if self._policy is None:
            self._paths = local_plan_paths(self.job.plan_paths, lambda: ray.get(self._plans[0]),
                                           DEFAULT_PLAN_CACHE / SHIPPED_PLANS)
            self._policy = open_policy(policy_config_for(self.job.policy, self.index), self.job.embodiment)
        return evaluate([], self.job.backend_for(self._paths), self._policy, self, self.job.run_id,
                        num_envs=self.job.num_envs, progress=self, episode_timeout_s=self.job.episode_timeout_s,
                        recorder_factory=self.job.recorder_factory, more=self._pull,
                        on_device=self.job.policy.get("on_device", "off"),
                        env_id_base=self.index * self.job.num_envs)  # workers may share one policy server

    def close(self) -> None:
        if self._policy is not None:
            self._policy.close()

    def _pull(self, n: int) -> list[PlannedEpisode]:
        import ray

        items = ray.get(self.dispatcher.pull.remote(self.index, n))
        return [replace(item, plan_path=Path(self._paths[item.plan_hash])) for item in items]

    # -- the loop's store (RowSink) and progress (ProgressSink) --

    def finished(self, run_id: str) -> set[EpisodeKey]:
        return set()  # the driver queued only what its store lacks

    def add_many(self, results: list[EpisodeResult]) -> int:
        import ray

        steps, self._steps, self._sent = self._steps, 0, time.monotonic()
        ray.get(self.dispatcher.report.remote(list(results), steps))
        return len(results)

    def episode_finished(self, row: EpisodeResult) -> None:
        """Counted by the driver, when it writes the row."""

    def interactions(self, n: int) -> None:
        self._steps += n
        if time.monotonic() - self._sent > COUNT_EVERY_S:
            self.dispatcher.count.remote(self._steps)  # no wait: a lost count only slows the rate shown
            self._steps, self._sent = 0, time.monotonic()
