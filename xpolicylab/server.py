"""The policy server: one Model behind a WebSocket, speaking the native (XPolicyLab) or the openpi dialect.

Design choices, and why:

* asyncio for the sockets, and every Model call on one dedicated worker thread: inference never blocks the
  event loop, so heartbeats and other clients keep flowing, and the model is never entered concurrently.
  Decoding stays on the event loop: it is one copy per array (tens of ms for a 180 MB batch), and handing it
  to a thread measured ~10% slower on two cores because the copy holds the GIL either way.
* Each native request is answered by its own task, so a ``heartbeat`` sent during a long ``infer`` is answered
  at once; requests reach the model in arrival order (one worker thread, FIFO).
* A malformed frame is answered with an ``error`` frame (native) or openpi's text-frame + close 1011, and only
  ever affects its own connection. Frames over ``max_frame_mb`` are refused by the WebSocket layer with close
  code 1009 before they are buffered.
* Environment ids are kept apart between clients (``xpolicylab.env_ids``): the model sees a client's ids as sent
  unless another open connection holds them, and forgets a connection's environments when it closes.
* Shared memory (``capabilities.shared_memory``, the ``shared_memory`` option): a client on this host may send
  large arrays as references to its own segments; each connection opens a segment once, and only a loopback
  peer's references are read (``xpolicylab.shm``). The arrays are copied out before the model sees them, unless it
  keeps none of them (``Model.borrows_observations``): then it reads them where the client wrote them.
* The optional token is checked during the HTTP upgrade (``Authorization: Bearer <t>`` or openpi's
  ``Api-Key <t>``) with a constant-time comparison; ``/healthz`` answers without one.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import hmac
import logging
import threading
import time
import traceback
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from http import HTTPStatus
from typing import Any

import numpy as np
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from xpolicylab import codec, columns, shm, transport
from xpolicylab.env_ids import ConnectionIds, EnvIdSpace
from xpolicylab.errors import ErrorCode, ProtocolError
from xpolicylab.model import Model, as_model
from xpolicylab.protocol import (PROTOCOL_VERSION, REQUESTS, SERVER_NAME, UPSTREAM_FORMAT, Frame, MessageType,
                                 decode_frame_or_error, encode_frame, error_for_unreadable)

logger = logging.getLogger(__name__)

PROTOCOLS = ("xpolicylab", "openpi")
#: First words of the line ``run_server`` prints once it listens; the URL ends the line.
READY_LINE = "xpolicylab serving"


@dataclass
class ServerConfig:
    """Everything ``xpolicylab serve`` can set besides the policy."""

    host: str = "127.0.0.1"
    port: int = 19000
    protocol: str = "xpolicylab"
    token: str | None = None
    max_frame_mb: float = 512.0
    request_timeout_s: float = 120.0
    ping_interval_s: float | None = 20.0
    ping_timeout_s: float | None = 120.0
    shared_memory: bool = True

    def __post_init__(self) -> None:
        if self.protocol not in PROTOCOLS:
            raise ValueError(f"protocol must be one of {PROTOCOLS}, got {self.protocol!r}")
        if self.max_frame_mb <= 0 or self.request_timeout_s <= 0:
            raise ValueError("max_frame_mb and request_timeout_s must be positive")


def token_matches(header: str | None, token: str) -> bool:
    """Constant-time check of an ``Authorization`` header against the configured token."""
    if not header:
        return False
    scheme, _, value = header.strip().partition(" ")
    if scheme.lower() not in ("bearer", "api-key"):
        return False
    return hmac.compare_digest(value.strip().encode(), token.encode())


def _as_actions(result: Any) -> np.ndarray:
    try:
        actions = np.asarray(result, dtype=np.float32)
    except (TypeError, ValueError) as exc:
        raise ProtocolError(ErrorCode.INFER_FAILED,
                            f"the model returned something that is not an action array: {exc}") from exc
    return actions


def _env_ids(payload: dict[str, Any], count: int) -> list[Any]:
    env_ids = payload.get("env_ids")
    if not isinstance(env_ids, list) or len(env_ids) != count:
        raise ProtocolError(ErrorCode.INVALID_FRAME, "a batched request needs 'env_ids', a list as long as "
                            "'observations'", {"field": "env_ids"})
    return _distinct_ids(env_ids)


def _distinct_ids(env_ids: list[Any]) -> list[Any]:
    """`env_ids` as given, once each is known to be a string or an integer and none repeats."""
    if not all(isinstance(e, (str, int)) and not isinstance(e, bool) for e in env_ids):
        raise ProtocolError(ErrorCode.INVALID_FRAME, "env ids must be strings or integers", {"field": "env_ids"})
    if len(set(env_ids)) != len(env_ids):
        raise ProtocolError(ErrorCode.INVALID_FRAME, "env ids must be distinct", {"field": "env_ids"})
    return env_ids


def _observations(payload: dict[str, Any]) -> tuple[list[dict[str, Any]], list[Any] | None]:
    """The request's observations and env ids (``None`` for a single observation)."""
    if "observations" in payload:
        obs_list = payload["observations"]
        if not isinstance(obs_list, list) or not obs_list or not all(isinstance(o, dict) for o in obs_list):
            raise ProtocolError(ErrorCode.INVALID_FRAME, "'observations' must be a non-empty list of maps",
                                {"field": "observations"})
        return obs_list, _env_ids(payload, len(obs_list))
    obs = payload.get("observation")
    if not isinstance(obs, dict):
        raise ProtocolError(ErrorCode.INVALID_FRAME, "infer payload needs 'observation' (a map), 'observations' + "
                            "'env_ids' or 'columns' + 'env_ids'", {"field": "observation"})
    return [obs], None


def _columns(payload: dict[str, Any]) -> tuple[dict[str, Any], list[Any]]:
    """A columnar request's columns and env ids, checked (``xpolicylab.columns``): one environment per env id."""
    if "observations" in payload or "observation" in payload:
        raise ProtocolError(ErrorCode.INVALID_FRAME, f"an infer payload carries {columns.KEY!r} or observations, "
                            "not both", {"field": columns.KEY})
    env_ids = payload.get("env_ids")
    if not isinstance(env_ids, list) or not env_ids:
        raise ProtocolError(ErrorCode.INVALID_FRAME, f"a columnar request needs 'env_ids', a non-empty list: its "
                            "length is the batch's", {"field": "env_ids"})
    columns.check(payload[columns.KEY], len(env_ids))
    return payload[columns.KEY], _distinct_ids(env_ids)


class _LetGo:
    """A call that lets go of ``fn`` (and what it closes over: a request's observations, perhaps views of a client's
    shared-memory segment) as it returns. The model's executor keeps its work item a moment after handing back the
    result; a connection closing in that moment would find its segment still lent out, keep it mapped and warn that
    the model kept what it borrowed."""

    def __init__(self, fn: Callable[[], Any]) -> None:
        self._fn: Callable[[], Any] | None = fn

    def __call__(self) -> Any:
        fn, self._fn = self._fn, None
        assert fn is not None, "a model call runs once"
        return fn()


class PolicyServer:
    """Serves one Model. Use ``await start()``/``stop()``, ``serve_forever()``, or ``ServerThread``."""

    def __init__(self, model: Model | Any, config: ServerConfig | None = None) -> None:
        self.model = as_model(model)
        self.config = config or ServerConfig()
        self.instance_id = uuid.uuid4().hex[:12]
        self._metadata = self.model.metadata
        self._worker = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="xpolicylab-model")
        self._server: Server | None = None
        self._env_ids = EnvIdSpace()

    @property
    def port(self) -> int:
        """The bound port (useful with ``port=0``)."""
        assert self._server is not None, "server not started"
        return self._server.sockets[0].getsockname()[1]

    @property
    def url(self) -> str:
        return f"ws://{self.config.host}:{self.port}"

    async def start(self) -> None:
        max_size = int(self.config.max_frame_mb * (1 << 20))
        self._server = await serve(
            self._handle, self.config.host, self.config.port, process_request=self._process_request,
            max_size=max_size, max_queue=64, ping_interval=self.config.ping_interval_s,
            ping_timeout=self.config.ping_timeout_s, **transport.CONNECTION_OPTIONS,
        )
        logger.info("serving %s (%s dialect) on %s", self._metadata.name, self.config.protocol, self.url)

    async def stop(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
            self._server = None
        self._worker.shutdown(wait=False, cancel_futures=True)

    async def serve_forever(self, on_ready: Callable[[str], None] | None = None) -> None:
        """Serve until cancelled; ``on_ready(url)`` runs once the socket is bound."""
        await self.start()
        assert self._server is not None
        if on_ready is not None:
            on_ready(self.url)
        try:
            await self._server.serve_forever()
        finally:
            await self.stop()

    def _process_request(self, connection: ServerConnection, request: Request) -> Response | None:
        if request.path.split("?")[0] == "/healthz":
            return connection.respond(HTTPStatus.OK, "ok\n")
        if self.config.token and not token_matches(request.headers.get("Authorization"), self.config.token):
            response = connection.respond(HTTPStatus.UNAUTHORIZED, "missing or invalid token\n")
            response.headers = Headers([*response.headers.raw_items(), ("WWW-Authenticate", "Bearer")])
            return response
        return None

    async def _handle(self, ws: ServerConnection) -> None:
        try:
            if self.config.protocol == "openpi":
                await self._serve_openpi(ws)
            else:
                await self._serve_native(ws)
        except ConnectionClosed:
            pass

    async def _call_model(self, fn: Callable[[], Any]) -> Any:
        loop = asyncio.get_running_loop()
        try:
            return await asyncio.wait_for(loop.run_in_executor(self._worker, _LetGo(fn)), self.config.request_timeout_s)
        except asyncio.TimeoutError:
            raise ProtocolError(ErrorCode.TIMEOUT,
                                f"the model took longer than {self.config.request_timeout_s} s") from None

    async def _infer(self, payload: dict[str, Any], ids: ConnectionIds) -> dict[str, Any]:
        model = self.model
        if columns.KEY in payload:
            batch, env_ids = _columns(payload)
            model_ids = ids.to_model(env_ids)

            def run() -> Any:
                model.update_obs_columns(batch, model_ids)
                return model.get_action_batch(model_ids)
        else:
            obs_list, env_ids = _observations(payload)
            model_ids = None if env_ids is None else ids.to_model(env_ids)

            def run() -> Any:
                if model_ids is None:
                    model.update_obs(obs_list[0])
                    return model.get_action()
                model.update_obs_batch(obs_list, model_ids)
                return model.get_action_batch(model_ids)

        start = time.perf_counter()
        try:
            result = await self._call_model(run)
        except ProtocolError:
            raise
        except Exception as exc:
            raise ProtocolError(ErrorCode.INFER_FAILED, f"{type(exc).__name__}: {exc}",
                                {"traceback": traceback.format_exc(limit=8)}) from exc
        latency_ms = (time.perf_counter() - start) * 1e3
        if isinstance(result, dict) and "actions" in result:  # XPolicyLab-style models return their own payload
            reply = dict(result)
        else:
            reply = {"actions": _as_actions(result)}
        reply.setdefault("action_mode", self._metadata.action_mode)
        reply.setdefault("latency_ms", latency_ms)
        if env_ids is not None:
            reply["env_ids"] = env_ids
        return reply

    def hello_payload(self) -> dict[str, Any]:
        """What ``hello_ack`` says about this server and its policy (``shared_memory`` only when on, so that a
        server with it off answers exactly as before it existed)."""
        capabilities: dict[str, Any] = {"batch_infer": True, "columnar_batch": True,
                                        "native_batch": self._metadata.batch,
                                        "max_frame_bytes": int(self.config.max_frame_mb * (1 << 20))}
        if self.config.shared_memory:
            capabilities["shared_memory"] = True
        return {
            "ok": True, "server": SERVER_NAME, "server_instance_id": self.instance_id,
            "protocol_version": PROTOCOL_VERSION, "wire_format": UPSTREAM_FORMAT, "metadata": self._metadata.to_dict(),
            "capabilities": capabilities,
        }

    def _shared_memory_refusal(self, ws: ServerConnection) -> str | None:
        """Why this connection's shared-memory references are refused, or ``None`` when they are read: only a
        peer on this host can have written into this host's segments, and only a loopback address proves it."""
        if not self.config.shared_memory:
            return "this server does not accept shared-memory references (it runs with shared_memory=false)"
        peer = ws.remote_address
        if not shm.is_loopback_address(peer):
            where = peer[0] if peer else peer
            return f"shared-memory references are accepted only from a loopback peer, not from {where}"
        return None

    async def _hook(self, name: str, arg: dict[str, Any], code: ErrorCode) -> dict[str, Any]:
        fn = getattr(self.model, name)
        try:
            result = await self._call_model(lambda: fn(arg))
        except ProtocolError:
            raise
        except Exception as exc:
            raise ProtocolError(code, f"{name} failed: {type(exc).__name__}: {exc}") from exc
        return {"ok": True} if result is None else {"ok": True, "result": result}

    async def _reset(self, frame: Frame, ids: ConnectionIds) -> dict[str, Any]:
        env_ids = frame.payload.get("env_ids")
        if env_ids is not None:
            if not isinstance(env_ids, list):
                raise ProtocolError(ErrorCode.INVALID_FRAME, "'env_ids' must be a list", {"field": "env_ids"})
            env_ids = ids.to_model(_distinct_ids(env_ids))
        model = self.model
        try:
            await self._call_model(model.reset if env_ids is None else (lambda: model.reset_batch(env_ids)))
        except ProtocolError:
            raise
        except Exception as exc:
            raise ProtocolError(ErrorCode.RESET_FAILED, f"reset failed: {type(exc).__name__}: {exc}") from exc
        return {"ok": True}

    async def _forget(self, ids: ConnectionIds) -> None:
        """A connection closed: its environments are released, and the model forgets them before another
        client is given their ids (the model's one worker thread runs requests in order)."""
        released = ids.release()
        if not released:
            return
        try:
            await self._call_model(lambda: self.model.reset_batch(released))
        except Exception as exc:  # the connection is gone: nobody to tell but the log
            logger.warning("forgetting the environments of a closed connection: %s: %s", type(exc).__name__, exc)

    async def _dispatch(self, frame: Frame, ids: ConnectionIds) -> Frame:
        kind = frame.message_type
        if kind is MessageType.HELLO:
            return frame.reply(MessageType.HELLO_ACK, self.hello_payload())
        if kind is MessageType.HEARTBEAT:
            return frame.reply(MessageType.HEARTBEAT_ACK, {"ok": True, "server_time": time.time()})
        if kind is MessageType.INFER:
            return frame.reply(MessageType.INFER_RESULT, await self._infer(frame.payload, ids))
        if kind is MessageType.RESET:
            return frame.reply(MessageType.RESET_RESULT, await self._reset(frame, ids))
        if kind is MessageType.PREPARE_CASE:
            meta = dict(frame.payload)
            if frame.action_case_id is not None:
                meta.setdefault("action_case_id", frame.action_case_id)
            return frame.reply(MessageType.PREPARE_CASE_ACK,
                               await self._hook("prepare_case", meta, ErrorCode.INTERNAL))
        if kind is MessageType.TRIAL_END:
            return frame.reply(MessageType.TRIAL_END_ACK,
                               await self._hook("on_trial_end", dict(frame.payload), ErrorCode.INTERNAL))
        raise ProtocolError(ErrorCode.UNKNOWN_MESSAGE_TYPE, f"{kind.value!r} is not a request a server answers",
                            {"message_type": kind.value, "requests": sorted(t.value for t in REQUESTS)})

    async def _respond(self, ws: ServerConnection, frame: Frame, segments: shm.SegmentCache,
                       ids: ConnectionIds) -> None:
        try:
            # Copies, so that the model keeps nothing of the client's segments, unless it keeps nothing anyway.
            segments.resolve(frame.payload, borrow=self.model.borrows_observations)
            reply = await self._dispatch(frame, ids)
        except ProtocolError as exc:
            reply = frame.error(exc)
        except Exception as exc:  # a bug in the server itself must not take the connection down silently
            logger.exception("internal error answering %s", frame.message_type.value)
            reply = frame.error(ProtocolError(ErrorCode.INTERNAL, f"{type(exc).__name__}: {exc}"))
        try:
            await transport.send_chunks(ws, encode_frame(reply))
        except ConnectionClosed:
            pass
        except (TypeError, ValueError) as exc:  # the model put something unencodable in its reply
            error = ProtocolError(ErrorCode.INFER_FAILED, f"reply cannot be encoded: {exc}")
            await transport.send_chunks(ws, encode_frame(frame.error(error)))

    async def _serve_native(self, ws: ServerConnection) -> None:
        tasks: set[asyncio.Task[None]] = set()
        segments = shm.SegmentCache(self._shared_memory_refusal(ws))
        ids = self._env_ids.connection()
        try:
            while True:
                is_text, parts = await transport.recv_message(ws)
                if is_text:
                    frame, error = None, error_for_unreadable(None, ProtocolError(
                        ErrorCode.INVALID_FRAME, "text frames are not part of the protocol; send binary MessagePack"))
                else:
                    frame, error = decode_frame_or_error(parts, shared_refs=True)
                if frame is None:
                    await transport.send_chunks(ws, encode_frame(error))
                    continue
                if frame.message_type is MessageType.CLOSE:
                    await ws.close(reason="client sent close")
                    return
                task = asyncio.create_task(self._respond(ws, frame, segments, ids))
                tasks.add(task)
                task.add_done_callback(tasks.discard)
        finally:
            if tasks:
                await asyncio.gather(*tasks, return_exceptions=True)
            segments.close()
            await self._forget(ids)

    async def _serve_openpi(self, ws: ServerConnection) -> None:
        await ws.send(codec.encode(self._metadata.to_dict(), codec.Dialect.OPENPI))
        ids = self._env_ids.connection()
        try:
            await self._answer_openpi(ws, ids)
        finally:
            await self._forget(ids)

    async def _answer_openpi(self, ws: ServerConnection, ids: ConnectionIds) -> None:
        while True:
            is_text, parts = await transport.recv_message(ws)
            try:
                if is_text:
                    raise ProtocolError(ErrorCode.INVALID_FRAME, "expected a binary MessagePack observation")
                obs = codec.decode(parts)
                if not isinstance(obs, dict):
                    raise ProtocolError(ErrorCode.INVALID_FRAME, "an observation must be a map")
                payload = obs if "observations" in obs else {"observation": obs}
                start = time.perf_counter()
                reply = await self._infer(payload, ids)
                reply["server_timing"] = {"infer_ms": (time.perf_counter() - start) * 1e3}
                await transport.send_chunks(ws, codec.encode_chunks(reply, codec.Dialect.OPENPI))
            except (ProtocolError, TypeError, ValueError) as exc:
                # openpi's convention: the error as a text frame, then close with 1011.
                await ws.send(f"{type(exc).__name__}: {exc}")
                await ws.close(code=1011, reason="Internal server error")
                return


class ServerThread:
    """Runs a PolicyServer on its own event loop in a daemon thread (tests, bench, checker self-tests).

    Use as a context manager; ``port=0`` picks a free port, read it from ``.port`` / ``.url``.
    """

    def __init__(self, model: Model, config: ServerConfig | None = None) -> None:
        self.server = PolicyServer(model, config)
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="xpolicylab-server", daemon=True)

    def __enter__(self) -> ServerThread:
        self._thread.start()
        asyncio.run_coroutine_threadsafe(self.server.start(), self._loop).result(timeout=30)
        return self

    def __exit__(self, *exc: object) -> None:
        asyncio.run_coroutine_threadsafe(self.server.stop(), self._loop).result(timeout=30)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=30)
        self._loop.close()

    @property
    def port(self) -> int:
        return self.server.port

    @property
    def url(self) -> str:
        return self.server.url


def run_server(model: Model, config: ServerConfig | None = None,
               on_ready: Callable[[str], None] | None = None) -> None:
    """Serve ``model`` until interrupted (Ctrl-C); ``on_ready(url)`` runs once it listens."""
    server = PolicyServer(model, config)

    def announce(url: str) -> None:
        # The bench and eval scripts wait for this exact line (READY_LINE) before connecting.
        print(f"{READY_LINE} {server.model.metadata.name} ({server.config.protocol}) on {url}", flush=True)

    try:
        asyncio.run(server.serve_forever(on_ready or announce))
    except KeyboardInterrupt:
        pass
