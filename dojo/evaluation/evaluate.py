"""The evaluation loop: plans in, one durable result row per episode out.

Environments run in slots of one backend. Each slot plays one episode: the policy is reset for it, asked for an
action chunk whenever the slot has none left, and the chunk is executed one control step at a time. When an
episode ends (success, horizon, a non-finite action, its wall-clock timeout, the policy failing on it) its row
is written to the results store at once, and the slot is refilled with the next queued episode, whatever its
task: the batch stays full and different tasks run side by side (continuous batching). Images are rendered only
for slots whose chunk has run out; the next plans are prefetched so that refills do not wait on compilation.

Resume: a run's id is derived from what it evaluates (suite, policy identity, backend, seeds, episode counts),
so re-running the same command finds the same run in the store and skips every episode already recorded. An
interrupted run loses at most the episodes that were still in flight; those are re-run from their start.

Launchers: the loop does not care where its episodes come from or where its rows go. `store` is anything with
`finished()` and `add_many()` and `progress` anything with `episode_finished()` and `interactions()`, and with
`more` the loop pulls further episodes as its slots free up, so that a Ray worker (`dojo.launch.ray_launcher`)
runs this same loop on episodes it pulls from the driver and streams its rows back, instead of a copy of it.

A policy in the backend (`on_device`): a policy that offers its rule as array code (`PolicyLink.device_rule`, the
built-in `zero` and `random` in joint mode), on a backend that can run it inside its own step (`mjx`), in a run that
records nothing and sends the policy no images, is attached to the backend before it loads, and the loop then steps
with it (`Backend.step_with_rule`): no chunk is asked for, no observation is built per step, no action is sent.
`policy.on_device` (`policy_link.ON_DEVICE`) says whether to (`policy_link.device_rule_for`).

Recording (optional): with a `recorder_factory`, every slot gets a recorder that sees each observation and the
action taken from it, and whose video path goes into the episode's row. The backend may then render cameras the
policy did not ask for; the policy is shown only its own (`metadata.cameras`).
"""

from __future__ import annotations

import bisect
import hashlib
import json
import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol

import numpy as np

from dojo.backends.base import Backend, StepResult
from xpolicylab.errors import ErrorCode, ProtocolError
from dojo.compiler.episodes import PlannedEpisode
from dojo.compiler.plan import Plan

from dojo.evaluation.chunks import ChunkQueue
from dojo.evaluation.episode import EpisodeKey, EpisodeResult, episode_key
from dojo.evaluation.policy_link import PolicyLink, device_rule_for
from dojo.evaluation.recorder import SlotRecorder

log = logging.getLogger(__name__)

TIMEOUT = "timeout"
POLICY_ERROR = "policy_error"


class Stopped(Exception):
    """The loop was told to stop (`evaluate`'s `stop`): the episodes it had in flight are not recorded, and a
    resumed run re-runs them, as after an interrupt."""


@dataclass
class _Slot:
    item: PlannedEpisode
    plan: Plan
    started: float


@dataclass
class _Latest:
    """Where each slot's episode stood after the last step, read only when it ends: the step's result and the
    slots it stepped (sorted, the result's order). Every running slot is stepped every tick, so one result holds
    them all; a slot refilled since has not stepped (`forget`), and an episode that ends before its first step has
    made no progress."""

    result: StepResult | None = None
    ids: list[int] = field(default_factory=list)
    refilled: set[int] = field(default_factory=set)

    def update(self, result: StepResult, ids: list[int]) -> None:
        self.result, self.ids, self.refilled = result, ids, set()

    def forget(self, ids: Iterable[int]) -> None:
        self.refilled.update(ids)

    def progress(self, i: int) -> tuple[float, int, dict[str, int | None], dict[str, bool], dict[str, int]]:
        """Slot i's score, steps, stage times, success terms and backend counters so far."""
        k, r = bisect.bisect_left(self.ids, i), self.result
        if r is None or i in self.refilled or k == len(self.ids) or self.ids[k] != i:
            return 0.0, 0, {}, {}, {}
        return (float(r.score[k]), int(r.steps[k]), r.stage_times[k], r.terms[k] if r.terms else {},
                r.counters[k] if r.counters else {})


class RowSink(Protocol):
    """Where finished episodes go: the results store, or a worker's link to the driver that writes them."""

    def finished(self, run_id: str) -> set[EpisodeKey]:
        """Keys of the episodes already recorded (skipped)."""

    def add_many(self, results: Sequence[EpisodeResult]) -> int:
        """Record episodes that ended together; return how many were new."""


class ProgressSink(Protocol):
    """What the loop reports as it goes: a `Progress`, or a worker's counter sent to the driver's."""

    def episode_finished(self, row: EpisodeResult) -> None: ...

    def interactions(self, n: int) -> None: ...


def run_id_for(identity: dict[str, Any]) -> str:
    """A stable id for what a run evaluates: the same command resumes the same run."""
    digest = hashlib.sha256(json.dumps(identity, sort_keys=True, default=str).encode()).hexdigest()
    return f"{identity.get('suite', 'run')}-{identity.get('policy', 'policy')}-{digest[:12]}"


class TimeSplit:
    """Wall seconds of a run's loop by phase, for one closing log line: which of the policy, the backend's steps
    and resets or the loop's own bookkeeping a run waits on is the first question when it is slow."""

    PHASES = ("load", "policy", "backend steps", "resets and records")

    def __init__(self) -> None:
        self.seconds: Counter[str] = Counter()
        self._start = time.perf_counter()

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] += time.perf_counter() - start

    def line(self, backend: str) -> str:
        """The closing line of the loop on `backend` (named: a run's routes each close with one)."""
        total = time.perf_counter() - self._start
        parts = [f"{name} {self.seconds[name]:.1f} s" for name in self.PHASES]
        rest = total - sum(self.seconds[name] for name in self.PHASES)
        return f"where the loop's {total:.1f} s on backend {backend} went: {', '.join(parts)}, the rest {rest:.1f} s"


def evaluate(queue: list[PlannedEpisode], backend_factory: Callable[[], Backend], policy: PolicyLink,
             store: RowSink, run_id: str, *, num_envs: int, progress: ProgressSink,
             episode_timeout_s: float | None = None,
             recorder_factory: Callable[[], SlotRecorder] | None = None,
             more: Callable[[int], list[PlannedEpisode]] | None = None, on_device: Any = "off",
             env_id_base: int = 0, stop: threading.Event | None = None) -> int:
    """Run every queued episode not yet in the store for `run_id`; return how many were run now.

    `more(n)` (optional) is asked for up to n further episodes whenever slots are free and the queue is empty
    ([] when there are none now): episodes are taken only when a slot can start them, so a worker of a launcher
    never holds episodes that another, idle worker could be running. `on_device` (auto | on | off): whether the
    policy's rule runs inside the backend's step (module docstring). The policy knows slot i as environment
    `env_id_base + i`: loops that share one policy server (a launcher's workers) give theirs disjoint ranges, or
    a policy that keeps state per environment (frames, memory) would see two episodes under one id. `stop`: once
    set (by another loop of the run, `side_by_side`), the loop raises `Stopped` before its next step."""
    finished = store.finished(run_id)
    todo = deque(item for item in queue if episode_key(item) not in finished)
    if more is not None and len(todo) < num_envs:
        todo.extend(more(num_envs - len(todo)))
    if not todo:
        return 0
    meta = policy.metadata
    policy_meta = meta.to_dict()
    backend = backend_factory()
    if backend.max_envs is not None:  # a robot is one slot, whatever num_envs the run was given
        num_envs = min(num_envs, backend.max_envs)
    plans: dict[Path, Plan] = {}

    def plan_of(item: PlannedEpisode) -> Plan:
        if item.plan_path not in plans:  # each plan file is read once; the backend caches compiled models
            plans[item.plan_path] = Plan.load(item.plan_path)
        return plans[item.plan_path]

    first = [todo.popleft() for _ in range(min(num_envs, len(todo)))]
    slots: dict[int, _Slot] = {i: _Slot(item, plan_of(item), time.monotonic()) for i, item in enumerate(first)}
    recorders = {i: recorder_factory() for i in slots} if recorder_factory else {}
    chunks = ChunkQueue(len(slots))  # the actions each slot is playing
    latest = _Latest()
    ran = 0
    split = TimeSplit()

    def addressed(ids: Iterable[int]) -> list[int]:
        """The environment ids the policy knows these slots by."""
        return [env_id_base + i for i in ids]

    def finish(ended: list[tuple[int, bool, str | None]], last_obs: dict[int, Any]) -> None:
        """Record ended episodes (durably, before anything else happens to their slots), then refill the slots
        from the queue or retire them."""
        nonlocal ran
        with split.phase("resets and records"):
            now = time.monotonic()
            rows = []
            for i, success, reason in ended:
                video = recorders[i].finish(last_obs[i], success)[0] if recorders else None
                rows.append(_row(run_id, slots[i], latest.progress(i), success, reason, meta.name, policy_meta,
                                 now, video, backend.name))
            store.add_many(rows)
            for row in rows:
                progress.episode_finished(row)
            ran += len(rows)
            ids = [i for i, _, _ in ended]
            latest.forget(ids)
            if more is not None and len(todo) < len(ids):
                todo.extend(more(len(ids) - len(todo)))
            refill = ids[:len(todo)]
            chunks.clear(np.asarray(ids, np.int64))
            for i in ids[len(refill):]:
                del slots[i]
                obs.pop(i, None)  # a retired slot's last images would hold their buffer to the end of the run
            if refill:
                items = [todo.popleft() for _ in refill]
                for i, item in zip(refill, items):
                    slots[i] = _Slot(item, plan_of(item), time.monotonic())
                    if recorders:
                        recorders[i].start(item, slots[i].plan)
                for i, first_obs in zip(refill, backend.reset(refill, [plan_of(it) for it in items])):
                    obs[i] = first_obs
                if rule is None:
                    policy.reset(addressed(refill))
                backend.prefetch([plan_of(todo[j]) for j in range(min(len(refill), len(todo)))])

    def host_step() -> StepResult | None:
        """One step with the policy asked on the host for the slots whose chunks ran out (None: it failed on
        them, and their episodes ended instead)."""
        ids = sorted(slots)
        stepped = np.asarray(ids, np.int64)
        need = stepped[chunks.exhausted(stepped)].tolist()
        if need:
            try:
                with split.phase("policy"):
                    answer = policy.act([_with_episode(obs[i], slots[i], meta.cameras) for i in need], addressed(need))
            except ProtocolError as err:
                if err.code != ErrorCode.INFER_FAILED:
                    raise  # the link itself failed: stop, and resume these episodes later
                finish([(i, False, f"{POLICY_ERROR}: {err}") for i in need], obs)  # the policy failed on them
                return None
            chunks.fill(np.asarray(need, np.int64), answer)
        actions = chunks.take(stepped)
        if recorders:
            for k, i in enumerate(ids):
                recorders[i].add(obs[i], actions[k])
        else:
            for i in need:  # asked: nothing reads these again, and kept they would hold their images (buffers
                del obs[i]  # the backend reuses) until the slot is next observed, steps later
        # Observations only where they will be looked at: a slot whose chunk just ran out, or every slot recorded.
        looked = range(len(ids)) if recorders else np.flatnonzero(chunks.exhausted(stepped)).tolist()
        with split.phase("backend steps"):
            result = backend.step(actions, ids, mode=meta.action_mode, observe=[ids[k] for k in looked])
        obs.update((ids[k], result.obs[k]) for k in looked)
        return result

    def device_step() -> StepResult:
        """One step with the policy's rule run by the backend, for every slot."""
        with split.phase("backend steps"):
            return backend.step_with_rule(sorted(slots))

    try:
        rule = device_rule_for(policy, backend.name, recording=recorder_factory is not None, on_device=on_device)
        if rule is not None:
            backend.attach_rule(rule)
            log.info("policy %s runs on the device: backend %s steps its rule itself (no observation out, no "
                     "action in)", meta.name, backend.name)
        elif meta.cameras and (buffers := policy.image_buffers()) is not None:
            backend.use_image_buffers(buffers)  # images copied off a GPU go to the policy where they lie
        for i, rec in recorders.items():
            rec.start(slots[i].item, slots[i].plan)
        with split.phase("load"):  # compiling included: the first tick of a batched backend may follow in a step
            backend.load([s.plan for s in slots.values()])
            obs = dict(zip(slots, backend.reset(list(slots))))
            if rule is None:
                policy.reset(addressed(slots))
            backend.prefetch([plan_of(todo[j]) for j in range(min(num_envs, len(todo)))])
        while slots:
            if stop is not None and stop.is_set():
                raise Stopped(f"{len(slots)} episode(s) in flight on backend {backend.name} left for a resumed run")
            result = host_step() if rule is None else device_step()
            if result is None:
                continue
            ids = sorted(slots)  # the slots just stepped, in the order of the result
            progress.interactions(len(ids))
            latest.update(result, ids)
            ending = np.asarray(result.done, bool)
            if episode_timeout_s is not None:
                now = time.monotonic()
                ending = ending | np.asarray([now - slots[i].started > episode_timeout_s for i in ids], bool)
            ended = [(ids[k], won, None if won else (result.end_reason[k] or TIMEOUT))
                     for k, won in zip(np.flatnonzero(ending).tolist(), result.success[ending].tolist())]
            if ended:
                finish(ended, obs)
    finally:
        for rec in recorders.values():
            rec.discard()  # only episodes still in flight have files open
        backend.close()
        log.info(split.line(backend.name))
    return ran


def _with_episode(obs: dict[str, Any], slot: _Slot, cameras: tuple[str, ...]) -> dict[str, Any]:
    """The runtime numbers episodes; the backend only knows the scene seed. Images of cameras rendered only for
    recording are not the policy's to see."""
    meta = dict(obs.get("meta", {}))
    meta["episode"] = slot.item.episode
    out = {**obs, "meta": meta}
    for key in ("images", "depth"):
        if key in obs:
            seen = {c: v for c, v in obs[key].items() if c in cameras}
            if seen:
                out[key] = seen
            else:
                del out[key]
    return out


def _row(run_id: str, slot: _Slot, progress: tuple[float, int, dict[str, int | None], dict[str, bool], dict[str, int]],
         success: bool, reason: str | None, policy_name: str, policy_meta: dict[str, Any], now: float,
         video_path: str | None, backend: str) -> EpisodeResult:
    item = slot.item
    score, steps, stage_times, terms, counters = progress
    return EpisodeResult(
        run_id=run_id, split=item.split, plan_hash=item.plan_hash, task=item.task, dimension=item.dimension,
        setting=item.setting, eval_seed=item.eval_seed, episode=item.episode, scene_seed=item.scene_seed,
        policy_name=policy_name, policy_meta=policy_meta, success=success, score=score, steps=steps,
        wall_time_s=now - slot.started, stage_times=stage_times, failure_reason=reason,
        video_path=video_path, success_terms=terms, counters=counters, backend=backend)
