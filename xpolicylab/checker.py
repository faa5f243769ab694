"""The offline checker: does a policy server answer correctly shaped observations with valid action chunks?

Run it before spending simulator or robot time on a policy. It drives the whole request sequence an
evaluation uses (hello, prepare_case, reset, infer x n, batched infer, heartbeat, trial_end) with synthetic
observations for a chosen embodiment and camera set, validates every reply, and prints a pass/fail report
with latency percentiles. In the native dialect it also lists every way the server's frames depart from
upstream XPolicyLab's wire format (``conformance``), each with how many replies showed it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from xpolicylab import codec
from xpolicylab.client import PolicyClient
from xpolicylab.conformance import array_departures, envelope_departures, payload_departures
from xpolicylab.embodiments import ACTION_MODES, CAMERAS, Embodiment, get_embodiment
from xpolicylab.errors import ErrorCode, ProtocolError
from xpolicylab.model import PolicyMetadata
from xpolicylab.observations import noise_images, synthetic_observation
from xpolicylab.protocol import UPSTREAM_FORMAT, Frame, is_batch, parse_frame

#: Slack on joint limits, radians: float32 rounding of a pose sitting exactly on its limit must pass.
LIMIT_TOL = 1e-3
#: Allowed deviation of an end-effector quaternion's norm from 1.
QUAT_TOL = 1e-2
MAX_PROBLEMS = 3


@dataclass
class CheckConfig:
    """What to check against."""

    url: str
    protocol: str = "xpolicylab"
    embodiment: str = "arx_x5_bimanual"
    cameras: tuple[str, ...] = CAMERAS
    width: int = 640
    height: int = 480
    n: int = 20
    batch: int = 4
    depth: bool = False
    token: str | None = None
    timeout_s: float = 30.0
    connect_attempts: int = 8  # with exponential backoff: about 15 s for a server that is still loading
    seed: int = 0


@dataclass
class CheckItem:
    name: str
    ok: bool
    detail: str = ""


@dataclass
class CheckReport:
    config: CheckConfig
    items: list[CheckItem] = field(default_factory=list)
    latency: dict[str, float] = field(default_factory=dict)

    @property
    def passed(self) -> bool:
        return bool(self.items) and all(item.ok for item in self.items)

    def add(self, name: str, problems: Sequence[str], detail: str = "", limit: int = MAX_PROBLEMS) -> bool:
        ok = not problems
        self.items.append(CheckItem(name, ok, detail if ok else "; ".join(problems[:limit])))
        return ok

    def format(self) -> str:
        c = self.config
        lines = [f"xpolicylab check {c.url} ({c.protocol} dialect, {c.embodiment}, cameras {','.join(c.cameras)} "
                 f"{c.width}x{c.height}, n={c.n})"]
        lines += [f"  {'PASS' if i.ok else 'FAIL'} {i.name:<14} {i.detail}".rstrip() for i in self.items]
        if self.latency.get("count"):
            lat = self.latency
            lines.append(f"  latency ms over {lat['count']} infers: p50 {lat['p50_ms']:.2f}  p90 {lat['p90_ms']:.2f}  "
                         f"p99 {lat['p99_ms']:.2f}  max {lat['max_ms']:.2f}")
        passed = sum(i.ok for i in self.items)
        lines.append(f"RESULT: {'PASS' if self.passed else 'FAIL'} ({passed}/{len(self.items)} checks passed)")
        return "\n".join(lines)


def validate_chunk(actions: Any, embodiment: Embodiment, mode: str, chunk_size: int | None = None) -> list[str]:
    """Every way ``actions`` breaks the action contract (empty when it is valid)."""
    if not isinstance(actions, np.ndarray):
        return [f"actions must be a numpy array, got {type(actions).__name__}"]
    if actions.dtype != np.float32:
        return [f"actions must be float32, got {actions.dtype}"]
    dim = embodiment.action_dim(mode)
    if actions.ndim != 2 or actions.shape[1] != dim or actions.shape[0] < 1:
        return [f"actions must be [K, {dim}] for {mode} mode, got {list(actions.shape)}"]
    problems = []
    if chunk_size is not None and actions.shape[0] != chunk_size:
        problems.append(f"chunk has {actions.shape[0]} rows, metadata promised chunk_size={chunk_size}")
    if not np.all(np.isfinite(actions)):
        bad = np.argwhere(~np.isfinite(actions))[0]
        return problems + [f"actions[{bad[0]}, {bad[1]}] is not finite"]
    if mode == "joint":
        lo, hi = embodiment.joint_bounds()
        outside = np.argwhere((actions < lo - LIMIT_TOL) | (actions > hi + LIMIT_TOL))
        for row, col in outside[:MAX_PROBLEMS]:
            problems.append(f"actions[{row}, {col}] = {actions[row, col]:.4f} outside [{lo[col]:.2f}, {hi[col]:.2f}]")
    else:
        arms = actions.reshape(actions.shape[0], 2, 8)
        quat_err = np.abs(np.linalg.norm(arms[:, :, 3:7], axis=2) - 1.0)
        if np.any(quat_err > QUAT_TOL):
            problems.append(f"end-effector quaternions must be unit length (worst |q|-1 = {quat_err.max():.3f})")
        reach = np.linalg.norm(arms[:, :, :3], axis=2)
        if np.any(reach > embodiment.reach_m):
            problems.append(f"end-effector position {reach.max():.2f} m from the base, beyond {embodiment.reach_m} m")
        grip = arms[:, :, 7]
        if np.any((grip < -LIMIT_TOL) | (grip > 1 + LIMIT_TOL)):
            problems.append("gripper values must lie in 0..1 (closed..open)")
    return problems


def _metadata_problems(meta: PolicyMetadata, emb: Embodiment, cfg: CheckConfig, declared: dict[str, Any]) -> list[str]:
    """Problems with what the server declared; fields it left out are not held against it."""
    problems = []
    if meta.action_mode not in ACTION_MODES:
        return [f"metadata action_mode {meta.action_mode!r} is not one of {ACTION_MODES}"]
    if "action_dim" in declared and meta.action_dim != emb.action_dim(meta.action_mode):
        problems.append(f"metadata action_dim {meta.action_dim} != {emb.action_dim(meta.action_mode)} "
                        f"for {emb.name} in {meta.action_mode} mode")
    if meta.embodiment not in (None, emb.name):
        problems.append(f"policy is for {meta.embodiment}, check runs {emb.name}")
    if int(meta.chunk_size) < 1:
        problems.append(f"metadata chunk_size {meta.chunk_size} must be at least 1")
    missing = [cam for cam in meta.cameras if cam not in cfg.cameras]
    if "cameras" in declared and missing:
        problems.append(f"policy expects cameras {missing} that the check does not send (cameras={list(cfg.cameras)})")
    if meta.image_width is not None and "image_width" in declared and \
            (meta.image_width, meta.image_height) != (cfg.width, cfg.height):
        problems.append(f"policy expects {meta.image_width}x{meta.image_height} images, check sends "
                        f"{cfg.width}x{cfg.height}")
    return problems


def _reply_problems(reply: dict[str, Any], emb: Embodiment, meta: PolicyMetadata, chunk_size: int | None) -> list[str]:
    mode = reply.get("action_mode", meta.action_mode)
    if mode != meta.action_mode:
        return [f"reply action_mode {mode!r} differs from metadata {meta.action_mode!r}"]
    return validate_chunk(reply.get("actions"), emb, meta.action_mode, chunk_size)


def _declared(client: PolicyClient, cfg: CheckConfig) -> dict[str, Any]:
    """The metadata fields the server actually sent (openpi servers send their own, often none of ours)."""
    info = client.server_info
    return dict(info.get("metadata") or {}) if cfg.protocol == "xpolicylab" else dict(info)


def _step(report: CheckReport, name: str, fn: Any, record: bool = True) -> tuple[bool, Any]:
    """Run one request; a raised error is a failed check rather than a crash. ``record`` adds a PASS item."""
    try:
        value = fn()
    except Exception as exc:  # the checker reports every failure mode of the server under test
        report.add(name, [f"{type(exc).__name__}: {exc}"])
        return False, None
    if record:
        report.add(name, [])
    return True, value


class WireAudit:
    """Collects the departures from the wire format of every reply the client receives, with their counts."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = {}
        self.replies = 0

    def __call__(self, raw: bytes, request: Frame | None) -> None:
        self.replies += 1
        try:
            wire = codec.decode(raw)
            departures = array_departures(raw)
            if not isinstance(wire, dict):
                raise ProtocolError(ErrorCode.INVALID_FRAME, "a frame must be a map")
            departures += envelope_departures(wire, request)
            batched = request is not None and is_batch(request.payload)
            departures += payload_departures(parse_frame(wire), batched)
        except ProtocolError as exc:
            departures = [f"frame: {exc.message}"]
        for departure in departures:
            self.counts[str(departure)] = self.counts.get(str(departure), 0) + 1

    def problems(self) -> list[str]:
        return [f"{text} ({count} of {self.replies} replies)" for text, count in self.counts.items()]


def _check_batch(report: CheckReport, name: str, client: PolicyClient, obs_list: list[dict[str, Any]],
                 emb: Embodiment, meta: PolicyMetadata, chunk_size: int) -> None:
    """One batched request of ``obs_list``, and its reply's chunks checked, as step ``name`` of ``report``."""
    count = len(obs_list)
    ok, batch = _step(report, name, lambda: client.infer_batch(obs_list, list(range(count))), record=False)
    if not ok:
        return
    dim = emb.action_dim(meta.action_mode)
    if not isinstance(batch, np.ndarray) or batch.ndim != 3 or batch.shape[0] != count:
        report.add(name, [f"batched reply must be [{count}, K, {dim}], got {list(getattr(batch, 'shape', []))}"])
        return
    how = ("one request each (no capabilities.batch_infer)" if not client.batches
           else "in one request, as columns" if client.sends_columns else "in one request")
    report.add(name, [f"env {i}: {p}" for i, chunk in enumerate(batch)
                      for p in validate_chunk(chunk, emb, meta.action_mode, chunk_size)], f"{count} environments {how}")


def run_check(cfg: CheckConfig) -> CheckReport:
    """Run the whole check against a live server."""
    report = CheckReport(cfg)
    emb = get_embodiment(cfg.embodiment)
    audit = WireAudit() if cfg.protocol == "xpolicylab" else None
    client = PolicyClient(cfg.url, cfg.protocol, token=cfg.token, recv_timeout_s=cfg.timeout_s,
                          connect_timeout_s=cfg.timeout_s, max_connect_attempts=cfg.connect_attempts,
                          observer=audit)
    try:
        ok, meta = _step(report, "connect", client.connect, record=False)
        if not ok:
            return report
        declared = _declared(client, cfg)
        chunk_size = int(meta.chunk_size) if "chunk_size" in declared else None
        if not report.add("metadata", _metadata_problems(meta, emb, cfg, declared),
                          f"policy {meta.name!r}, {meta.action_mode} mode, chunk {chunk_size or 'undeclared'}, "
                          f"D={meta.action_dim}, batch={'yes' if meta.batch else 'no'}"):
            return report
        if not _step(report, "prepare_case", lambda: client.prepare_case({"task": "xpolicylab_check"}, "check"))[0]:
            return report
        if not _step(report, "reset", lambda: client.reset("check-trial", repeat_index=0))[0]:
            return report
        images = noise_images(cfg.cameras, cfg.width, cfg.height, cfg.seed)
        problems: list[str] = []
        for step in range(cfg.n):
            obs = synthetic_observation(emb, cfg.cameras, cfg.width, cfg.height, depth=cfg.depth, step=step,
                                        seed=cfg.seed, images=images)
            ok, reply = _step(report, "infer", lambda obs=obs, step=step: client.infer_raw(obs, step),
                            record=False)
            if not ok:
                return report
            problems += [f"step {step}: {p}" for p in _reply_problems(reply, emb, meta, chunk_size)]
        report.latency = client.stats.summary()
        report.add("infer", problems, f"{cfg.n} chunks valid")
        if cfg.batch > 0 and (cfg.protocol == "xpolicylab" or meta.batch):
            obs_list = [synthetic_observation(emb, cfg.cameras, cfg.width, cfg.height, depth=cfg.depth, episode=i,
                                              seed=cfg.seed + i, images=images) for i in range(cfg.batch)]
            # Both forms of a batch a server advertises: the list, and the columns where it reads them.
            forms = [("infer_batch", False)] + [("infer_columns", True)] * client.sends_columns
            for name, columnar in forms:
                client.columnar = columnar
                _check_batch(report, name, client, obs_list, emb, meta, chunk_size)
        if cfg.protocol == "xpolicylab":
            _step(report, "heartbeat", client.heartbeat)
        _step(report, "trial_end", lambda: client.trial_end({"success": False, "score": 0.0}))
    finally:
        client.close()
        if audit is not None and audit.replies:
            problems = audit.problems()
            report.add("wire format", problems, f"{audit.replies} replies follow {UPSTREAM_FORMAT}", limit=len(problems))
    return report
