"""`dojo collect task=NAME n=100`: demonstrations of one task for training.

A demonstrator policy (the scripted `oracle`, or any policy the config names) runs the task's plans through the
same evaluation loop as `dojo run` (continuous batching, a durable row per episode), with a recorder per slot
that streams every step into an HDF5 episode: RGB(-D) of the configured cameras at the configured resolution,
joint states, end-effector poses, grippers, the action executed (next-step action), instruction, scene seed and
plan hash (`hdf5_episode`). When all are in, the LeRobot v3.0 dataset is built from those files
(`lerobot_dataset`), and the task's demo lengths and auto horizon are merged into the horizons file that
`dojo compile` and `dojo run` read (`datasets/horizons.json` by default).

Any task with training data can be collected: the five scored dimensions except Open (evaluation only), and the
training-only DLC tasks, whose episode rows here are never part of a score.

Scene seeds are `seed_offset + k`, far from the evaluation seeds. With `only_success`, failed episodes are not
kept and new seeds are drawn until `n` demonstrations are kept (or `max_attempts` episodes were run).

Resumable: the episode rows live in `<out>/collect.sqlite` under an id derived from what is collected (task,
policy, setting, cameras, resolution, ...). Re-running the same command skips every finished episode and
re-records only those that were in flight; a larger `n` extends the collection.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from dojo.backends.mujoco.render import ensure_headless_gl
from dojo.backends.registry import factory_from_config
from dojo.compiler.horizon import DEFAULT_HORIZONS, HORIZONS_FORMAT, auto_horizon

from dojo.compiler.episodes import PlannedEpisode
from dojo.evaluation.evaluate import run_id_for
from dojo.evaluation.policy_link import is_privileged
from dojo.evaluation.recorder import SlotRecorder

FORMATS = ("hdf5", "lerobot")


def write_horizons(path: Path, task: str, lengths: list[int], *, auto_generated: bool) -> dict[str, Any]:
    """Record a task's demo lengths and auto horizon in `path` (other tasks' entries are kept), for the suite
    compiler to read in place of `horizon_fallback`."""
    data = json.loads(path.read_text()) if path.exists() else {"format": HORIZONS_FORMAT, "tasks": {}}
    entry = {"demo_lengths": [int(n) for n in lengths], "auto_generated": auto_generated,
             "horizon": auto_horizon(lengths, auto_generated)}
    data["tasks"][task] = entry
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)
    return entry


class DemoRecorder:
    """The recorder of one slot while collecting: each episode streams into `<dir>/episode_<k>.hdf5`; a failed
    episode is dropped when only successes are kept."""

    def __init__(self, episodes_dir: Path, cameras: tuple[str, ...], *, depth: bool, action_mode: str,
                 policy: str, only_success: bool) -> None:
        self.episodes_dir, self.cameras, self.depth = episodes_dir, cameras, depth
        self.action_mode, self.policy, self.only_success = action_mode, policy, only_success
        self._writer: Any = None

    def start(self, item: PlannedEpisode, plan: Any) -> None:
        from dojo.datagen.hdf5_episode import Hdf5EpisodeWriter

        self.discard()
        attrs = {"task": plan.task, "instruction": plan.instruction, "setting": plan.setting, "seed": plan.seed,
                 "plan_hash": plan.hash, "embodiment": plan.embodiment, "action_mode": self.action_mode,
                 "control_hz": plan.control_hz, "policy": self.policy}
        self._writer = Hdf5EpisodeWriter(episode_path(self.episodes_dir, item.episode), self.cameras,
                                         depth=self.depth, attrs=attrs)

    def add(self, obs: dict[str, Any], action: np.ndarray) -> None:
        self._writer.append(obs, action)

    def finish(self, last_obs: dict[str, Any], success: bool) -> tuple[str | None, str | None]:
        writer, self._writer = self._writer, None
        if self.only_success and not success:
            writer.abort()
            return None, None
        return None, str(writer.close(success=success))

    def discard(self) -> None:
        if self._writer is not None:
            self._writer.abort()
            self._writer = None


def episode_path(episodes_dir: Path, k: int) -> Path:
    """The HDF5 file of the k-th episode attempted (scene seed `seed_offset + k`)."""
    return episodes_dir / f"episode_{k:06d}.hdf5"


def compile_plans(library: Any, task: Any, setting: str, seeds: list[int], out: Path, jobs: int | str
                  ) -> list[tuple[Path, str]]:
    """(plan file, hash) per scene seed, compiling those not yet in `out` (named as the suite compiler names
    them, so a plan is found again by its hash)."""
    from dojo.compiler.plan import plan_hash
    from dojo.compiler.episodes import Episode
    from dojo.compiler.suite_compile import compile_plan_files, plan_path

    dimension = task.data["dimension"]
    plans, todo = [], []
    for seed in seeds:
        digest = plan_hash(library, task, setting, seed)
        path = plan_path(out, Episode(task.id, dimension, setting, seed, 0, 0), digest)
        plans.append((path, digest))
        if not path.exists():
            todo.append((task.id, task.package, setting, seed, str(path)))
    compile_plan_files(library, todo, jobs=jobs)
    return plans


def _backend_factory(cfg: DictConfig, metadata: Any, plan_paths: dict[str, str]) -> Callable[[], Any]:
    """The configured backend rendering the collected cameras (and any the demonstrator reads); only a privileged
    demonstrator (the oracle) is shown the simulator state."""
    if cfg.backend.name != "mujoco":
        raise ValueError(f"dojo collect: backend '{cfg.backend.name}' cannot collect yet; use backend=mujoco")
    cameras = tuple(cfg.cameras) + tuple(c for c in metadata.cameras if c not in cfg.cameras)
    return factory_from_config(OmegaConf.to_container(cfg.backend, resolve=True), cameras=cameras,
                               width=int(cfg.width), height=int(cfg.height), depth=bool(cfg.depth),
                               privileged=is_privileged(metadata), plan_paths=plan_paths)


def collect_task(cfg: DictConfig) -> int:
    """The `dojo collect` job."""
    ensure_headless_gl()
    from dojo.compiler.spec_library import SpecLibrary

    from dojo.compiler.taxonomy import taxonomy_of

    from dojo.evaluation.evaluate import evaluate
    from dojo.evaluation.policy_link import open_policy, policy_identity
    from dojo.evaluation.progress import Progress
    from dojo.evaluation.results_store import ResultsStore
    from dojo.cli.run_cmd import DEFAULT_PLAN_CACHE

    if OmegaConf.is_missing(cfg, "task"):
        raise ValueError("dojo collect: name the task to demonstrate, e.g. task=stack_blocks")
    formats = [str(f) for f in cfg.format]
    if not formats or set(formats) - set(FORMATS):
        raise ValueError(f"format must be a non-empty subset of {list(FORMATS)}, got {formats}")
    if cfg.setting not in ("standard", "random"):
        raise ValueError(f"setting must be standard or random, got {cfg.setting!r}")
    n = int(cfg.n)
    if n < 1:
        raise ValueError(f"n must be at least 1, got {n}")
    max_attempts = int(cfg.max_attempts) if cfg.max_attempts is not None else 3 * n
    packs = [Path(p) for p in cfg.packs]
    library = SpecLibrary.load(packs)
    task = library.get("task", str(cfg.task))
    dimension = task.data["dimension"]
    # Evaluation-only dimensions (RoboDojo's Open) test what no demonstration showed: their tasks are refused.
    # Training-only ones (DLC) are collected like the scored ones; that is all they are for.
    if dimension in taxonomy_of(library).evaluation_only:
        raise ValueError(f"dojo collect: task {task.id} is in dimension '{dimension}', which is evaluation only: "
                         "its tasks have no training demonstrations (RoboDojo's protocol)")
    out = Path(cfg.out) if cfg.out else Path("datasets") / task.id
    episodes_dir = out / "hdf5" if "hdf5" in formats else out / ".episodes"
    plan_dir = Path(cfg.plans) if cfg.plans else DEFAULT_PLAN_CACHE / f"collect-{task.id}"

    policy_cfg = OmegaConf.to_container(cfg.policy, resolve=True)
    assert isinstance(policy_cfg, dict)
    policy = open_policy(policy_cfg, task.data["embodiment"])
    meta = policy.metadata
    identity = {"collect": task.id, "policy": meta.name, "policy_config": policy_identity(policy_cfg),
                "setting": cfg.setting, "seed_offset": int(cfg.seed_offset), "cameras": list(cfg.cameras),
                "width": int(cfg.width), "height": int(cfg.height), "depth": bool(cfg.depth),
                "only_success": bool(cfg.only_success)}
    run_id = run_id_for({"suite": task.id, **identity})

    def recorder() -> SlotRecorder:
        return DemoRecorder(episodes_dir, tuple(cfg.cameras), depth=bool(cfg.depth), action_mode=meta.action_mode,
                            policy=meta.name, only_success=bool(cfg.only_success))

    queue: list[PlannedEpisode] = []
    plan_paths: dict[str, str] = {}
    out.mkdir(parents=True, exist_ok=True)
    try:
        with ResultsStore(out / "collect.sqlite") as store:
            others = [r for r in store.run_ids() if r != run_id]
            if others:
                raise ValueError(f"{out} holds a collection made with other settings ({store.run_meta(others[0])}); "
                                 "use another out= folder")
            store.ensure_run(run_id, identity)
            while True:
                rows = sorted((r for r in store.rows(run_id) if r.episode < len(queue)), key=lambda r: r.episode)
                kept = [r for r in rows if r.success or not cfg.only_success]
                missing = n - len(kept)
                if queue and (missing <= 0 or len(queue) >= max_attempts):
                    break
                start = len(queue)
                seeds = [int(cfg.seed_offset) + k for k in range(start, min(start + max(missing, 0), max_attempts))]
                for k, (path, digest) in enumerate(compile_plans(library, task, str(cfg.setting), seeds, plan_dir,
                                                                 cfg.jobs), start):
                    plan_paths[digest] = str(path)
                    queue.append(PlannedEpisode(task=task.id, dimension=task.data["dimension"],
                                                setting=str(cfg.setting), scene_seed=int(cfg.seed_offset) + k,
                                                eval_seed=0, episode=k, plan_hash=digest, plan_path=path))
                finished = [r for r in store.rows(run_id) if r.episode < len(queue)]  # resumed: counted as done
                with Progress(len(queue), mode=str(cfg.progress), finished=finished) as progress:
                    evaluate(queue, _backend_factory(cfg, meta, plan_paths), policy, store, run_id,
                             num_envs=int(cfg.num_envs), progress=progress, recorder_factory=recorder)
    finally:
        policy.close()

    kept = kept[:n]
    files = [episode_path(episodes_dir, r.episode) for r in kept]
    summary: dict[str, Any] = {"task": task.id, "kept": len(kept), "attempted": len(rows),
                               "successes": sum(r.success for r in rows), "episodes": str(episodes_dir),
                               "frames": sum(r.steps for r in kept)}
    if "lerobot" in formats and files:
        summary["lerobot"] = str(_lerobot(out / "lerobot", files, kept, fps=round(_control_hz(files[0]))))
    lengths = [r.steps for r in kept if r.success]
    if lengths:
        horizons_path = Path(cfg.horizons) if cfg.horizons else DEFAULT_HORIZONS
        entry = write_horizons(horizons_path, task.id, lengths, auto_generated=bool(task.data.get("auto_generated")))
        summary.update(horizon=entry["horizon"], horizons=str(horizons_path))
    print(json.dumps(summary))
    return 0 if len(kept) >= n else 1


def _control_hz(path: Path) -> float:
    import h5py

    with h5py.File(path, "r") as f:
        return float(f.attrs["control_hz"])


def _lerobot(root: Path, files: list[Path], kept: list[Any], *, fps: int) -> Path:
    """Build the LeRobot dataset unless the one at `root` already holds exactly these episodes."""
    import pyarrow.parquet as pq

    from dojo.datagen.lerobot_dataset import EPISODES_PATH, write_lerobot

    existing = root / EPISODES_PATH.format(chunk_index=0, file_index=0)
    seeds = [r.scene_seed for r in kept]
    if existing.exists() and pq.read_table(existing, columns=["robodojo/seed"]).column(0).to_pylist() == seeds:
        return root
    write_lerobot(root, files, fps=fps)
    return root
