"""One RealEval session at the robot: a real suite's trials, run one at a time by an operator, each recorded.

The session owns the robot (the `real` backend, the emulator by default) and one thread that alone drives it:
the operator's Reset (lay the next trial's scene out: release an e-stop, put the arms at the start pose; the
emulator also puts the objects where the plan says) and Start (run the trial through the ordinary evaluation loop,
`dojo.evaluation.evaluate`, into the results store, with a video of every camera) are queued to that thread, so
the cameras are only ever rendered from it. Stop and E-stop act at once from any thread: the backend ends the
trial at its next step, and an e-stop holds the arms, then returns them slowly to the reset pose. With
`serve_estop()`, the e-stop also has a process of its own (`dojo.realeval.estop`), started when the robot
connects, which holds the arms without waiting for this one.

Blindness: each trial has a `code` drawn from a secret of the session, and nothing the session shows (trial
list, state, rater pages) names the policy or the run, whose id and folder do; the results store keeps both, and
the ratings join them there (`dojo.realeval.ratings`).

Layout replay: `record_layout()` keeps the live frames of the trial's scene as its reference (one PNG per camera
and the object list, under `layouts/<task>/<setting>-<scene seed>/`), and `alignment()` says how closely the live
view matches the reference now, as the operator moves objects to match the overlay.
"""

from __future__ import annotations

import hashlib
import json
from queue import Queue
import secrets
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dojo.backends.real.piper_driver import PiperDriver
from dojo.backends.registry import BackendOptions, make_backend
from dojo.compiler.plan import Plan
from dojo.evaluation.episode import EpisodeResult
from dojo.compiler.episodes import PlannedEpisode
from dojo.evaluation.evaluate import evaluate
from dojo.evaluation.policy_link import PolicyLink
from dojo.evaluation.recorder import EpisodeRecorder
from dojo.evaluation.results_store import ResultsStore
from dojo.realeval.estop import EstopProcess

QUEUED, READY, RUNNING, DONE = "queued", "ready", "running", "done"


@dataclass
class Trial:
    """One trial of the session: its blind `code`, the episode it runs, and where it stands."""

    code: str
    item: PlannedEpisode
    status: str = QUEUED
    end_reason: str | None = None
    steps: int = 0
    video: Path | None = None
    counters: dict[str, int] = field(default_factory=dict)

    def public(self) -> dict[str, Any]:
        """What operators and raters may see of the trial (no policy, no run)."""
        return {"code": self.code, "task": self.item.task, "trial": self.item.episode, "status": self.status,
                "end_reason": self.end_reason, "steps": self.steps, "video": self.video is not None,
                "counters": self.counters}


class _Lease:
    """The session's robot lent to one trial's evaluation loop, which closes its backend when it is done: here
    that only ends the loan, the robot stays connected (and an e-stop's return home goes on). Every observation
    the loop gets is kept as the live view."""

    def __init__(self, session: ConsoleSession) -> None:
        self._session = session
        self._backend = session.backend

    def __getattr__(self, name: str) -> Any:
        return getattr(self._backend, name)

    def reset(self, *args: Any, **kwargs: Any) -> list[dict[str, Any]]:
        observations = self._backend.reset(*args, **kwargs)
        self._session._seen(observations[0])
        return observations

    def step(self, *args: Any, **kwargs: Any) -> Any:
        result = self._backend.step(*args, **kwargs)
        self._session._seen(result.obs[0], steps=int(result.steps[0]))
        return result

    def close(self) -> None:
        """The loop is done with the robot; the session keeps it."""


class _Progress:
    """The evaluation loop's progress sink: the trial's row, when it ends."""

    def __init__(self) -> None:
        self.rows: list[EpisodeResult] = []

    def episode_finished(self, row: EpisodeResult) -> None:
        self.rows.append(row)

    def interactions(self, n: int) -> None:
        """Counted by the live view instead (steps of the running trial)."""


class ConsoleSession:
    """A real suite's trials at one robot. `queue` is the suite's compiled episodes, in protocol order."""

    def __init__(self, queue: Sequence[PlannedEpisode], policy: PolicyLink, run_id: str, store_path: Path,
                 out_dir: Path, backend: dict[str, Any], cameras: Sequence[str], size: tuple[int, int],
                 layouts: Path) -> None:
        """`backend`: the `backend=real` config (name and settings); `cameras` rendered at `size` (the policy's
        and every camera of the robot, all filmed); `layouts`: the reference layouts' folder."""
        self.policy, self.run_id, self.store_path, self.out_dir = policy, run_id, store_path, out_dir
        self.layouts, self.cameras = layouts, tuple(cameras)
        secret = secrets.token_hex(16)
        self.trials = [Trial(_blind_code(secret, item), item) for item in queue]
        self._by_code = {t.code: t for t in self.trials}
        settings = {k: v for k, v in backend.items() if k != "name"}
        self.backend = make_backend(str(backend["name"]), BackendOptions(
            cameras=self.cameras, width=size[0], height=size[1], settings=settings))
        self.current: Trial | None = None
        self.live: dict[str, np.ndarray] = {}
        self.step = 0
        self.error: str | None = None
        self._plans: dict[Path, Plan] = {}
        self._estop_settings: tuple[str, str, str, int] | None = None
        self.estop_process: EstopProcess | None = None
        self._work: Queue[Callable[[], None] | None] = Queue()
        self._thread = threading.Thread(target=self._drive, name="dojo-console-robot", daemon=True)
        self._thread.start()

    # ---- what the operator does ----

    def trial(self, code: str) -> Trial:
        if code not in self._by_code:
            raise KeyError(f"no trial {code!r} in this session")
        return self._by_code[code]

    def next_trial(self) -> Trial | None:
        return next((t for t in self.trials if t.status in (QUEUED, READY)), None)

    def reset(self, code: str) -> None:
        """Lay out `code`'s scene: release an e-stop and put the robot at the trial's start (queued)."""
        trial = self.trial(code)
        if trial.status not in (QUEUED, READY) or self.running:
            raise RuntimeError(f"trial {code} cannot be reset now ({trial.status})")
        self._work.put(lambda: self._reset(trial))

    def start(self, code: str) -> None:
        """Run `code` (queued behind its reset): the policy drives the robot until the trial ends."""
        trial = self.trial(code)
        if trial.status != READY or self.running:
            raise RuntimeError(f"trial {code} is {trial.status}: reset its scene first")
        trial.status = RUNNING
        self._work.put(lambda: self._run(trial))

    def stop(self) -> None:
        """End the running trial at its next step; the arms hold where they are."""
        self.backend.request_stop()

    def estop(self) -> float:
        """Disable policy control now and return the arms slowly to the reset pose; the time it took hold."""
        return self.backend.safety.estop() if self.backend.safety is not None else time.monotonic()

    def serve_estop(self, token: str, cookie: str, host: str, port: int) -> None:
        """Give the e-stop its own process once the robot is connected, if its driver speaks on CAN buses a
        second connection can reach (PiPER): presses with `token` (header or login `cookie`) on host:port."""
        self._estop_settings = (token, cookie, host, port)

    @property
    def running(self) -> bool:
        return self.current is not None and self.current.status == RUNNING

    # ---- layouts ----

    def layout_dir(self, trial: Trial) -> Path:
        return self.layouts / trial.item.task / f"{trial.item.setting}-{trial.item.scene_seed}"

    def record_layout(self, code: str) -> Path:
        """Keep the live frames of `code`'s scene as its reference layout, with the scene's object list."""
        from PIL import Image

        trial = self.trial(code)
        if self.current is not trial or not self.live:
            raise RuntimeError(f"trial {code}'s scene is not the one laid out: reset it first")
        folder = self.layout_dir(trial)
        folder.mkdir(parents=True, exist_ok=True)
        for camera, image in self.live.items():
            Image.fromarray(image).save(folder / f"{camera}.png")
        plan = self.plan(trial.item)  # the sampled objects and where the plan puts them
        (folder / "objects.json").write_text(json.dumps({"task": trial.item.task, "instruction": plan.instruction,
                                                         "objects": plan.scene.get("objects", [])}, indent=1,
                                                        default=str))
        return folder

    def reference(self, code: str, camera: str) -> Path | None:
        path = self.layout_dir(self.trial(code)) / f"{camera}.png"
        return path if path.is_file() else None

    def alignment(self, code: str) -> dict[str, float]:
        """Per camera, 100 x (1 - mean absolute pixel difference / 255) of the live view against the reference:
        100 when the scene matches it exactly."""
        from PIL import Image

        out = {}
        for camera, live in self.live.items():
            path = self.reference(code, camera)
            if path is not None:
                ref = np.asarray(Image.open(path).convert("RGB"), dtype=np.float32)
                if ref.shape == live.shape:
                    out[camera] = round(100.0 * (1.0 - float(np.abs(ref - live).mean()) / 255.0), 1)
        return out

    # ---- state ----

    def state(self) -> dict[str, Any]:
        """The live state the console shows (no policy, no run)."""
        safety = self.backend.safety
        out: dict[str, Any] = {"trial": None if self.current is None else self.current.public(), "step": self.step,
                               "cameras": list(self.cameras),
                               "safety": "disconnected" if safety is None else safety.state,
                               "counters": {} if safety is None else dict(safety.counters), "error": self.error,
                               "estop_port": None if self.estop_process is None else self.estop_process.port}
        driver = getattr(self.backend, "_driver", None)
        if driver is not None:
            joints = driver.read().joint_pos
            out["joint_pos"] = np.round(joints, 4).tolist()
            out["from_reset_pose_rad"] = round(float(np.abs(joints - driver.home_pose[0]).max()), 4)
        return out

    def close(self) -> None:
        """End a running trial, disconnect the robot (from its own thread, where its cameras render) and the
        policy."""
        if self.running:
            self.stop()
        if self.estop_process is not None:
            self.estop_process.close()
        self._work.put(self.backend.close)
        self._work.put(None)
        self._thread.join(timeout=60)
        self.policy.close()

    # ---- the robot's thread ----

    def _drive(self) -> None:
        while (job := self._work.get()) is not None:
            try:
                job()
            except Exception as exc:  # shown on the console; the session goes on with the next command
                self.error = f"{type(exc).__name__}: {exc}"
                if self.current is not None and self.current.status == RUNNING:
                    self.current.status, self.current.end_reason = READY, f"error: {exc}"

    def plan(self, item: PlannedEpisode) -> Plan:
        """The trial's plan (read once)."""
        if item.plan_path not in self._plans:
            self._plans[item.plan_path] = Plan.load(item.plan_path)
        return self._plans[item.plan_path]

    def _reset(self, trial: Trial) -> None:
        if self.backend.safety is not None:
            self.backend.safety.release()
        plan = self.plan(trial.item)
        if self.backend.num_envs == 0:
            self.backend.load([plan])
            self._start_estop_process()
        self._seen(self.backend.reset([0], [plan])[0])
        if self.current is not None and self.current is not trial and self.current.status == READY:
            self.current.status = QUEUED  # its scene is no longer the one laid out
        self.current, self.error = trial, None
        trial.status = READY

    def _start_estop_process(self) -> None:
        driver = getattr(self.backend, "_driver", None)
        if self._estop_settings is None or not isinstance(driver, PiperDriver) or self.backend.safety is None:
            return
        token, cookie, host, port = self._estop_settings
        self.estop_process = EstopProcess(driver, token, cookie, host, port, on_press=lambda _: self.estop())
        self.backend.safety.remote_halt = self.estop_process.halt

    def _run(self, trial: Trial) -> None:
        progress = _Progress()
        recorder = lambda: EpisodeRecorder(self.out_dir, self.cameras,  # noqa: E731
                                           action_mode=self.policy.metadata.action_mode,
                                           relative_to=self.store_path.parent)
        with ResultsStore(self.store_path) as store:
            evaluate([trial.item], lambda: _Lease(self), self.policy, store, self.run_id, num_envs=1,
                     progress=progress, recorder_factory=recorder)
        row = progress.rows[-1] if progress.rows else None
        trial.status = DONE
        if row is not None:
            trial.end_reason, trial.steps, trial.counters = row.failure_reason, row.steps, dict(row.counters)
            trial.video = self.store_path.parent / row.video_path if row.video_path else None

    def _seen(self, obs: dict[str, Any], steps: int | None = None) -> None:
        if "images" in obs:
            self.live = {c: obs["images"][c] for c in self.cameras if c in obs["images"]}
        if steps is not None:
            self.step = steps


def _blind_code(secret: str, item: PlannedEpisode) -> str:
    """A trial's public name: unguessable without the session's secret, so it says nothing of the policy."""
    key = f"{secret}:{item.plan_hash}:{item.eval_seed}:{item.episode}".encode()
    return hashlib.sha256(key).hexdigest()[:10]
