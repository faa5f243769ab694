"""The client the runtime (and the checker) uses to talk to a policy server, in either dialect.

* ``AsyncPolicyClient`` for asyncio code, ``PolicyClient`` (same methods, blocking) for everything else.
* Connecting retries with exponential backoff, because a policy server often needs a while to load weights.
* Every reply has a deadline (``recv_timeout_s``): a silent server raises ``ProtocolError(timeout)`` instead of
  hanging an evaluation.
* If the connection drops, the client reconnects, repeats ``hello`` and the current ``prepare_case`` (the
  trial's identifiers are kept), and retries the request once, so the current trial resumes.
* Native dialect: replies are matched to requests by ``message_id``, so a heartbeat can run during an infer.
  A reply that cannot be used (not a frame, or a malformed field: see ``conformance``) fails its request at
  once with the field and the reason; one whose ``message_id`` cannot be read fails every pending request.
  Servers that do not advertise ``capabilities.batch_infer`` (upstream XPolicyLab's) get one ``infer`` per
  environment; a batch larger than a frame may be (``capabilities.max_frame_bytes``) goes as several requests.
  openpi dialect: lock-step ``infer`` only; ``reset``/``prepare_case``/``trial_end`` have no openpi
  counterpart and are local no-ops.
* ``shared_memory`` (``auto``: when the server is on this host and advertises it; ``on``; ``off``): an infer
  request's large arrays go through ``/dev/shm`` instead of the socket (``xpolicylab.shm``); native dialect only.
* ``columnar`` (on by default): a batch whose observations share one layout goes as columns (``xpolicylab.columns``)
  to a server that advertises ``capabilities.columnar_batch``: one array per camera for the whole batch instead of
  one per environment.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
import urllib.parse
import uuid
from collections.abc import Awaitable, Callable, Hashable, Sequence
from typing import Any, TypeVar

import numpy as np
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus

from xpolicylab import codec, columns, shm, transport
from xpolicylab.conformance import fatal_problem
from xpolicylab.errors import ErrorCode, ProtocolError
from xpolicylab.model import Observation, PolicyMetadata
from xpolicylab.protocol import (PLACEHOLDER_ID, REPLY_TO, Frame, MessageType, encode_frame, is_batch,
                                 parse_frame, readable_ids)
from xpolicylab.stats import LatencyStats

logger = logging.getLogger(__name__)
T = TypeVar("T")
#: Sees every binary message the server sends, with the request it answers (``None`` when none matched).
ReplyObserver = Callable[[bytes, "Frame | None"], None]


class AuthError(ConnectionError):
    """The server refused our token (HTTP 401); retrying cannot help."""


class AsyncPolicyClient:
    """Asyncio client. ``await connect()`` first (or ``async with``)."""

    def __init__(
        self,
        url: str,
        protocol: str = "xpolicylab",
        *,
        token: str | None = None,
        evaluation_id: str | None = None,
        connect_timeout_s: float = 10.0,
        recv_timeout_s: float = 60.0,
        max_connect_attempts: int = 5,
        backoff_s: float = 0.2,
        backoff_max_s: float = 5.0,
        max_frame_mb: float = 512.0,
        observer: ReplyObserver | None = None,
        shared_memory: str | bool = "auto",
        columnar: bool = True,
    ) -> None:
        if protocol not in ("xpolicylab", "openpi"):
            raise ValueError(f"protocol must be 'xpolicylab' or 'openpi', got {protocol!r}")
        self.shared_memory = shm.mode(shared_memory)
        if protocol == "openpi" and self.shared_memory == "on":
            raise ValueError("shared_memory=on needs the xpolicylab dialect; openpi servers do not read references")
        self.columnar = columnar
        self.url = url
        self.protocol = protocol
        self.token = token
        self.evaluation_id = evaluation_id or uuid.uuid4().hex[:12]
        self.connect_timeout_s = connect_timeout_s
        self.recv_timeout_s = recv_timeout_s
        self.max_connect_attempts = max_connect_attempts
        self.backoff_s = backoff_s
        self.backoff_max_s = backoff_max_s
        self.max_size = int(max_frame_mb * (1 << 20))
        self.stats = LatencyStats()
        self.reconnects = 0
        self.metadata: PolicyMetadata | None = None
        self.server_info: dict[str, Any] = {}
        self._ws: ClientConnection | None = None
        self._reader: asyncio.Task[None] | None = None
        self.observer = observer
        self._pending: dict[str, tuple[Frame, asyncio.Future[Frame]]] = {}
        self._lockstep = asyncio.Lock()
        self._reconnecting = asyncio.Lock()
        self._case: tuple[str | None, dict[str, Any]] | None = None
        self._trial: dict[str, Any] = {}
        self._segments: shm.SegmentPool | None = None
        self._shared = False

    async def __aenter__(self) -> AsyncPolicyClient:
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # ----------------------------------------------------------------------------------------------- connection
    async def _open(self) -> ClientConnection:
        headers = {"Authorization": f"Bearer {self.token}"} if self.token else None
        delay, last = self.backoff_s, None
        for attempt in range(self.max_connect_attempts):
            try:
                return await asyncio.wait_for(
                    connect(self.url, additional_headers=headers, max_size=self.max_size, max_queue=64,
                            open_timeout=self.connect_timeout_s, ping_interval=20, ping_timeout=120,
                            **transport.CONNECTION_OPTIONS),
                    self.connect_timeout_s,
                )
            except InvalidStatus as exc:
                if exc.response.status_code == 401:
                    raise AuthError(f"{self.url} refused the token (HTTP 401)") from exc
                last = exc
            except (OSError, InvalidHandshake, asyncio.TimeoutError) as exc:
                last = exc
            if attempt + 1 < self.max_connect_attempts:
                await asyncio.sleep(delay)
                delay = min(delay * 2, self.backoff_max_s)
        raise ConnectionError(f"could not connect to {self.url} after {self.max_connect_attempts} attempts: {last}")

    async def connect(self) -> PolicyMetadata:
        """Connect (with retries), read the server's metadata, and replay the current case after a reconnect.
        Connecting again closes the current connection first (left open, it kept its server waiting on it)."""
        if self._ws is not None:
            await self.close()
        self._ws = await self._open()
        if self.protocol == "openpi":
            raw = await self._recv_openpi()
            if not isinstance(raw, dict):
                raise ProtocolError(ErrorCode.INVALID_FRAME, "openpi server metadata is not a map")
            self.server_info = raw
            self.metadata = PolicyMetadata.from_dict(raw)
            return self.metadata
        self._reader = asyncio.create_task(self._read_loop(self._ws))
        ack = await self._request(MessageType.HELLO, {"client": "xpolicylab", "protocol_version": "1.0"}, retry=False)
        self.server_info = ack.payload
        # Upstream XPolicyLab servers send no metadata: name the policy after the server, keep the defaults.
        declared = {"name": str(ack.payload.get("server", "unknown")), **(ack.payload.get("metadata") or {})}
        self.metadata = PolicyMetadata.from_dict(declared)
        await self._negotiate_shared_memory()
        if self._case is not None:
            case_id, meta = self._case
            await self._request(MessageType.PREPARE_CASE, meta, action_case_id=case_id, retry=False)
        return self.metadata

    async def close(self) -> None:
        """Say ``close`` (native) and disconnect; pending requests fail; shared-memory segments are unlinked."""
        ws, self._ws = self._ws, None
        self._shared = False
        if self._segments is not None:
            self._segments.close()
        if ws is not None:
            if self.protocol == "xpolicylab":
                try:
                    await ws.send(b"".join(encode_frame(Frame(MessageType.CLOSE, {"reason": "client done"},
                                                                   evaluation_id=self.evaluation_id))))
                except ConnectionClosed:
                    pass
            await ws.close()
        if self._reader is not None:
            self._reader.cancel()
            self._reader = None
        self._fail_pending(ConnectionError("client closed"))

    async def _negotiate_shared_memory(self) -> None:
        """Use shared memory on this connection when the option allows it and it works: the URL's host is loopback,
        the server advertises it, and a probe (a heartbeat carrying one reference) was read by the server, which
        a server in a container may fail to do (same loopback, another /dev/shm). With ``on``, anything else is an
        error now rather than a slow evaluation later."""
        self._shared = False
        if self.shared_memory == "off":
            return
        problem = self._shared_memory_obstacle() or await self._probe_shared_memory()
        if problem is None:
            self._shared = True
        elif self.shared_memory == "on":
            await self.close()
            raise ConnectionError(f"shared_memory=on, but {problem}")
        else:
            logger.info("%s: arrays go through the socket, not shared memory: %s", self.url, problem)

    def _shared_memory_obstacle(self) -> str | None:
        """Why shared memory cannot be used with this server, from what is known without trying."""
        host = urllib.parse.urlsplit(self.url).hostname
        if not shm.is_loopback_host(host):
            return f"the server's host {host!r} is not a loopback address"
        if (self.server_info.get("capabilities") or {}).get("shared_memory") is not True:
            return "the server does not advertise capabilities.shared_memory"
        return None

    async def _probe_shared_memory(self) -> str | None:
        """Why the server could not read an array through shared memory, or ``None`` when it could."""
        try:
            with self._pool().lease({"probe": np.zeros(shm.THRESHOLD, np.uint8)}) as payload:
                await self._request(MessageType.HEARTBEAT, payload, retry=False)
        except shm.NoSharedMemory as exc:
            return str(exc)
        except ProtocolError as exc:
            return f"the server could not read a shared-memory probe: {exc.message}"
        return None

    def _pool(self) -> shm.SegmentPool:
        if self._segments is None:
            self._segments = shm.SegmentPool()
        return self._segments

    async def _reconnect(self) -> None:
        """Open a fresh connection unless a concurrent request already did."""
        async with self._reconnecting:
            if self._ws is not None and self._ws.state.name == "OPEN":
                return
            old, self._ws = self._ws, None
            if old is not None:
                await old.close()
            if self._reader is not None:
                self._reader.cancel()
                self._reader = None
            self.reconnects += 1
            await self.connect()

    def _fail_pending(self, exc: BaseException) -> None:
        for _, fut in self._pending.values():
            if not fut.done():
                fut.set_exception(exc)
        self._pending.clear()

    def _fail(self, message_id: Any, exc: ProtocolError) -> None:
        """Fail the request ``message_id`` answers, or every pending request when it names none of them."""
        entry = self._pending.pop(str(message_id), None) if message_id != PLACEHOLDER_ID else None
        if entry is None:
            self._fail_pending(exc)
        elif not entry[1].done():
            entry[1].set_exception(exc)

    def _deliver(self, parts: list[bytes | str]) -> None:
        """Route one binary message to the request it answers, failing that request if the reply is unusable."""
        try:
            wire = codec.decode(parts)
        except ProtocolError as exc:
            self._fail_pending(ProtocolError(ErrorCode.INVALID_FRAME,
                                             f"the server sent a message that cannot be decoded: {exc.message}"))
            return
        try:
            frame = parse_frame(wire)
        except ProtocolError as exc:
            self._fail(readable_ids(wire)[0], ProtocolError(
                ErrorCode.INVALID_FRAME, f"malformed reply from the server: {exc.message}", exc.details))
            return
        if frame.message_type is MessageType.ERROR:
            err = ProtocolError(_code(frame.payload.get("code")), str(frame.payload.get("message", "")),
                                frame.payload.get("details") or {})
            self._fail(frame.message_id, err)  # an error naming no request: the server could not read ours
            return
        entry = self._pending.pop(str(frame.message_id), None)
        if entry is None or entry[1].done():
            return
        request, fut = entry
        problem = fatal_problem(frame, batched=is_batch(request.payload))
        if problem is None:
            fut.set_result(frame)
        else:
            fut.set_exception(ProtocolError(ErrorCode.INVALID_FRAME, f"{frame.message_type.value} from the server: "
                                            f"field {problem.field!r} {problem.message}", {"field": problem.field}))

    async def _read_loop(self, ws: ClientConnection) -> None:
        try:
            while True:
                is_text, parts = await transport.recv_message(ws)
                if is_text:
                    continue
                if self.observer is not None:
                    raw = b"".join(bytes(p) for p in parts)
                    self.observer(raw, self._request_of(raw))
                self._deliver(parts)
        except ConnectionClosed as exc:
            self._fail_pending(ConnectionError(f"connection closed: {exc}"))

    def _request_of(self, raw: bytes) -> Frame | None:
        """The pending request a raw reply names, for the observer (before delivery removes it)."""
        try:
            message_id = readable_ids(codec.decode(raw))[0]
        except ProtocolError:
            return None
        entry = self._pending.get(str(message_id))
        return entry[0] if entry is not None else None

    # ----------------------------------------------------------------------------------------------- requests
    async def _request(self, kind: MessageType, payload: dict[str, Any], *, step: int = 0,
                       action_case_id: str | None = None, retry: bool = True) -> Frame:
        for attempt in (0, 1):
            if self._ws is None:
                await self._reconnect()
            assert self._ws is not None
            ws = self._ws
            frame = Frame(kind, payload, evaluation_id=self.evaluation_id, step=step,
                          action_case_id=action_case_id if action_case_id is not None
                          else self._trial.get("action_case_id"),
                          trial_id=self._trial.get("trial_id"), repeat_index=self._trial.get("repeat_index"))
            fut: asyncio.Future[Frame] = asyncio.get_running_loop().create_future()
            self._pending[frame.message_id] = (frame, fut)
            try:
                await transport.send_chunks(ws, encode_frame(frame))
                reply = await asyncio.wait_for(fut, self.recv_timeout_s)
            except asyncio.TimeoutError:
                self._pending.pop(frame.message_id, None)
                raise ProtocolError(ErrorCode.TIMEOUT,
                                    f"no {REPLY_TO[kind].value} within {self.recv_timeout_s} s") from None
            except (ConnectionClosed, ConnectionError):
                self._pending.pop(frame.message_id, None)
                if not retry or attempt:
                    raise
                if self._ws is ws:
                    self._ws = None
                continue
            if reply.message_type is not REPLY_TO[kind]:
                raise ProtocolError(ErrorCode.INVALID_FRAME, f"expected {REPLY_TO[kind].value}, got "
                                    f"{reply.message_type.value}")
            return reply
        raise AssertionError("unreachable")

    async def _recv_openpi(self) -> Any:
        assert self._ws is not None
        try:
            is_text, parts = await asyncio.wait_for(transport.recv_message(self._ws), self.recv_timeout_s)
        except asyncio.TimeoutError:
            raise ProtocolError(ErrorCode.TIMEOUT, f"no reply within {self.recv_timeout_s} s") from None
        if is_text:
            raise ProtocolError(ErrorCode.INFER_FAILED, f"server error: {''.join(parts)}")
        return codec.decode(parts)

    async def _openpi_infer(self, request: dict[str, Any]) -> dict[str, Any]:
        async with self._lockstep:
            for attempt in (0, 1):
                try:
                    if self._ws is None:
                        await self._reconnect()
                    assert self._ws is not None
                    await transport.send_chunks(self._ws, codec.encode_chunks(request, codec.Dialect.OPENPI))
                    reply = await self._recv_openpi()
                    break
                except ConnectionClosed:
                    if attempt:
                        raise
                    self._ws = None
            if not isinstance(reply, dict) or "actions" not in reply:
                raise ProtocolError(ErrorCode.INVALID_FRAME, "openpi reply has no 'actions'")
            return reply

    async def _timed(self, call: Awaitable[T]) -> T:
        start = time.perf_counter()
        result = await call
        self.stats.record((time.perf_counter() - start) * 1e3)
        return result

    # ----------------------------------------------------------------------------------------------- public API
    async def prepare_case(self, meta: dict[str, Any], action_case_id: str | None = None) -> dict[str, Any]:
        """Announce an evaluation case; remembered so a reconnect can replay it."""
        self._case = (action_case_id, dict(meta))
        self._trial["action_case_id"] = action_case_id
        if self.protocol == "openpi":
            return {"ok": True}
        return (await self._request(MessageType.PREPARE_CASE, dict(meta), action_case_id=action_case_id)).payload

    async def reset(self, trial_id: str | None = None, *, repeat_index: int | None = None,
                    env_ids: Sequence[Hashable] | None = None) -> dict[str, Any]:
        """Start a trial (all environments, or only ``env_ids``)."""
        self._trial.update(trial_id=trial_id, repeat_index=repeat_index)
        if self.protocol == "openpi":
            return {"ok": True}
        payload: dict[str, Any] = {} if trial_id is None else {"trial_id": trial_id}
        if env_ids is not None:
            payload["env_ids"] = list(env_ids)
        return (await self._request(MessageType.RESET, payload)).payload

    async def _infer(self, payloads: Callable[[], list[dict[str, Any]]], step: int) -> list[Frame]:
        """Send the ``infer`` requests ``payloads()`` makes, together, and return their replies in order.

        With shared memory, every request's arrays are placed before any request is sent: when ``/dev/shm`` is
        full, nothing has reached the model yet, and (``auto``) the requests are made again for the socket and its
        frame budget; shared memory stays off from then on. With ``on`` the error is raised instead."""
        try:
            return await self._send_infers(payloads(), step)
        except shm.NoSharedMemory as exc:
            if self.shared_memory == "on":
                raise
            logger.warning("%s; arrays go through the socket from now on", exc)
            self._shared = False
            return await self._send_infers(payloads(), step)

    async def _send_infers(self, payloads: list[dict[str, Any]], step: int) -> list[Frame]:
        with contextlib.ExitStack() as leases:
            wires = [leases.enter_context(self._lease(p)) for p in payloads]
            return list(await asyncio.gather(*(self._request(MessageType.INFER, w, step=step) for w in wires)))

    def _lease(self, payload: dict[str, Any]) -> contextlib.AbstractContextManager[dict[str, Any]]:
        """The payload as it goes on the wire: through shared memory when this connection uses it."""
        return self._pool().lease(payload) if self._shared else contextlib.nullcontext(payload)

    async def infer_raw(self, obs: Observation, step: int = 0) -> dict[str, Any]:
        """One observation in, the full reply payload out (``actions``, ``action_mode``, ...)."""
        if self.protocol == "openpi":
            return await self._timed(self._openpi_infer(obs))
        (reply,) = await self._timed(self._infer(lambda: [{"observation": obs}], step))
        return reply.payload

    async def infer(self, obs: Observation, step: int = 0) -> np.ndarray:
        """One observation in, one action chunk ``float32[K, D]`` out."""
        return np.asarray((await self.infer_raw(obs, step))["actions"])

    async def infer_batch(self, obs_list: Sequence[Observation], env_ids: Sequence[Hashable],
                          step: int = 0) -> np.ndarray:
        """Many environments in one request, ``float32[B, K, D]`` out (looped for servers without batching)."""
        if len(obs_list) != len(env_ids):
            raise ValueError("obs_list and env_ids must have the same length")
        if not self.batches:
            return np.stack([await self.infer(o, step) for o in obs_list])
        if self.protocol == "openpi":
            request = {"observations": list(obs_list), "env_ids": list(env_ids)}
            return np.asarray((await self._timed(self._openpi_infer(request)))["actions"])
        replies = await self._timed(self._infer(lambda: self._batch_payloads(obs_list, env_ids), step))
        return np.concatenate([np.asarray(r.payload["actions"]) for r in replies])

    def _batch_payloads(self, obs_list: Sequence[Observation], env_ids: Sequence[Hashable]) -> list[dict[str, Any]]:
        """One ``infer`` payload per run of environments that fits in a frame (``frame_budget``): as columns when the
        server reads them and the observations share one layout, else as a list."""
        batch = columns.gather(obs_list) if self.sends_columns else None
        if batch is None:
            sizes = [observation_bytes(o, shared=self._shared) for o in obs_list]
            return [{"observations": list(obs_list[a:b]), "env_ids": list(env_ids[a:b])}
                    for a, b in batch_spans(sizes, self.frame_budget())]
        payloads = []
        for a, b in batch_spans(column_entry_bytes(batch, len(obs_list), self._shared), self.frame_budget()):
            part = columns.take(batch, a, b)
            # Through shared memory a column of arrays is placed row run by row run (shm.SegmentPool.lease).
            wire = part if self._shared else columns.joined(part)
            payloads.append({columns.KEY: wire, "env_ids": list(env_ids[a:b])})
        return payloads

    def frame_budget(self) -> int:
        """Bytes of observations one request may carry: the smaller of our limit and the one the server advertises
        (``capabilities.max_frame_bytes``), less 1/16 for the frame's own fields. A batch over it travels as
        several requests, sent together (their replies are matched by ``message_id``): one 640x480 batch of 256
        environments with three cameras is 708 MB, over the default 512 MiB, and the server would close the
        connection with 1009 instead. With shared memory, an observation counts only what still travels through
        the socket (``observation_bytes(shared=True)``)."""
        limit = self.max_size
        advertised = (self.server_info.get("capabilities") or {}).get("max_frame_bytes")
        if isinstance(advertised, int) and advertised > 0:
            limit = min(limit, advertised)
        return limit - limit // 16

    @property
    def uses_shared_memory(self) -> bool:
        """Whether large arrays of infer requests go through shared memory on the current connection."""
        return self._shared

    def lend_shared(self, nbytes: int) -> np.ndarray | None:
        """A buffer in shared memory for arrays this client will send (``shm.SegmentPool.lend``): one that lies in it
        in one piece goes as a reference, with no copy. None when this connection does not use shared memory."""
        return self._pool().lend(nbytes) if self._shared else None

    def give_back_shared(self, buffer: np.ndarray) -> None:
        """Unlink the segment of a buffer from ``lend_shared``."""
        self._pool().give_back(buffer)

    @property
    def sends_columns(self) -> bool:
        """Whether a batch goes as columns: the option is on and the server advertises ``columnar_batch``."""
        capabilities = self.server_info.get("capabilities") or {}
        return self.columnar and self.protocol == "xpolicylab" and capabilities.get("columnar_batch") is True

    @property
    def batches(self) -> bool:
        """Whether the server answers a batched ``infer`` (else ``infer_batch`` sends one request per env)."""
        if self.protocol == "openpi":
            return bool(self.metadata and self.metadata.batch)
        return (self.server_info.get("capabilities") or {}).get("batch_infer") is True

    async def trial_end(self, result: dict[str, Any]) -> dict[str, Any]:
        """Report a trial's outcome to the policy."""
        if self.protocol == "openpi":
            return {"ok": True}
        return (await self._request(MessageType.TRIAL_END, dict(result))).payload

    async def heartbeat(self) -> float:
        """Round trip of a heartbeat in milliseconds (openpi: not supported, returns NaN)."""
        if self.protocol == "openpi":
            return float("nan")
        start = time.perf_counter()
        await self._request(MessageType.HEARTBEAT, {})
        return (time.perf_counter() - start) * 1e3


#: The map msgpack-numpy writes around an array's data (keys, dtype, shape), counted with shared memory only: it is
#: nothing beside images, but about as much as a small array once the images are references.
ARRAY_FRAMING = 48


def observation_bytes(value: Any, shared: bool = False) -> int:
    """About how many bytes ``value`` takes on the wire: its arrays' and strings' payloads (the msgpack framing
    around them is a few bytes each, covered by the budget's margin). ``shared``: the large arrays go through
    shared memory, and the frame holds their references and every array's framing."""
    if isinstance(value, np.ndarray):
        if not shared:
            return value.nbytes
        return shm.REFERENCE_BYTES if shm.travels_shared(value) else value.nbytes + ARRAY_FRAMING
    if isinstance(value, (bytes, bytearray, memoryview, str)):
        return len(value)
    if isinstance(value, dict):
        return sum(observation_bytes(k) + observation_bytes(v, shared) for k, v in value.items())
    if isinstance(value, (list, tuple)):
        return sum(observation_bytes(v, shared) for v in value)
    return 8


def column_entry_bytes(batch: dict[str, Any], count: int, shared: bool = False) -> list[int]:
    """``observation_bytes`` of each environment's share of a columnar batch (``columns.gather``): the rows of its
    array columns (none when they go through shared memory) and its entries of the other columns."""
    fixed, lists = 0, []
    stack = [batch]
    while stack:
        node = stack.pop()
        for key, value in node.items():
            fixed += observation_bytes(key)
            if isinstance(value, dict):
                stack.append(value)
            elif isinstance(value, columns.Rows):
                fixed += 0 if shared and shm.travels_shared(value) else value.row_nbytes
            else:
                lists.append(_entry_bytes(value, shared))
    return [fixed + sum(sizes) for sizes in zip(*lists)] if lists else [fixed] * count


def _entry_bytes(column: list[Any], shared: bool) -> list[int]:
    """``observation_bytes`` of each entry of a list column; a column of strings or of numbers (instructions,
    episode numbers: thousands of entries per batch) without a call per entry."""
    kinds = set(map(type, column))
    if kinds <= {str}:
        return list(map(len, column))
    if kinds <= {int, float, bool, type(None)}:
        return [8] * len(column)
    return [observation_bytes(v, shared) for v in column]


def batch_spans(sizes: Sequence[int], budget: int) -> list[tuple[int, int]]:
    """Split environments of ``sizes`` bytes into consecutive ``(start, stop)`` runs of at most ``budget`` bytes.

    One observation over the budget alone cannot be sent: that is refused here, with both sizes, rather than by
    the server closing the connection."""
    spans: list[tuple[int, int]] = []
    start, total = 0, 0
    for i, size in enumerate(sizes):
        if size > budget:
            raise ProtocolError(ErrorCode.INVALID_FRAME, f"one observation is {size / (1 << 20):.1f} MiB, over the "
                                f"{budget / (1 << 20):.1f} MiB a request may carry (max_frame_mb of client and server)")
        if total + size > budget and i > start:
            spans.append((start, i))
            start, total = i, 0
        total += size
    spans.append((start, len(sizes)))
    return spans


def _code(value: Any) -> ErrorCode:
    try:
        return ErrorCode(value)
    except ValueError:
        return ErrorCode.INTERNAL


class PolicyClient:
    """Blocking twin of ``AsyncPolicyClient`` (same constructor and methods), run on a private event loop."""

    def __init__(self, url: str, protocol: str = "xpolicylab", **kwargs: Any) -> None:
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="xpolicylab-client", daemon=True)
        self._thread.start()
        self._client = self._run(self._make(url, protocol, kwargs))

    @staticmethod
    async def _make(url: str, protocol: str, kwargs: dict[str, Any]) -> AsyncPolicyClient:
        return AsyncPolicyClient(url, protocol, **kwargs)

    def _run(self, coro: Awaitable[T]) -> T:
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result()  # type: ignore[arg-type]

    def __enter__(self) -> PolicyClient:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def metadata(self) -> PolicyMetadata | None:
        return self._client.metadata

    @property
    def server_info(self) -> dict[str, Any]:
        return self._client.server_info

    @property
    def stats(self) -> LatencyStats:
        return self._client.stats

    @property
    def reconnects(self) -> int:
        return self._client.reconnects

    @property
    def sends_columns(self) -> bool:
        return self._client.sends_columns

    @property
    def columnar(self) -> bool:
        return self._client.columnar

    @columnar.setter
    def columnar(self, value: bool) -> None:
        self._client.columnar = value

    @property
    def batches(self) -> bool:
        return self._client.batches

    @property
    def uses_shared_memory(self) -> bool:
        return self._client.uses_shared_memory

    def lend_shared(self, nbytes: int) -> np.ndarray | None:
        return self._client.lend_shared(nbytes)

    def give_back_shared(self, buffer: np.ndarray) -> None:
        self._client.give_back_shared(buffer)

    def frame_budget(self) -> int:
        return self._client.frame_budget()

    def connect(self) -> PolicyMetadata:
        return self._run(self._client.connect())

    def close(self) -> None:
        """Disconnect and stop the private loop; the client cannot be used afterwards."""
        if self._loop.is_closed():
            return
        try:
            self._run(self._client.close())
        finally:
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout=10)
            self._loop.close()

    def _call(self, method: Callable[..., Awaitable[T]], *args: Any, **kwargs: Any) -> T:
        return self._run(method(*args, **kwargs))

    def prepare_case(self, meta: dict[str, Any], action_case_id: str | None = None) -> dict[str, Any]:
        return self._call(self._client.prepare_case, meta, action_case_id)

    def reset(self, trial_id: str | None = None, **kwargs: Any) -> dict[str, Any]:
        return self._call(self._client.reset, trial_id, **kwargs)

    def infer_raw(self, obs: Observation, step: int = 0) -> dict[str, Any]:
        return self._call(self._client.infer_raw, obs, step)

    def infer(self, obs: Observation, step: int = 0) -> np.ndarray:
        return self._call(self._client.infer, obs, step)

    def infer_batch(self, obs_list: Sequence[Observation], env_ids: Sequence[Hashable], step: int = 0) -> np.ndarray:
        return self._call(self._client.infer_batch, obs_list, env_ids, step)

    def trial_end(self, result: dict[str, Any]) -> dict[str, Any]:
        return self._call(self._client.trial_end, result)

    def heartbeat(self) -> float:
        return self._call(self._client.heartbeat)
