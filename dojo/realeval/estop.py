"""The console's e-stop, in a process of its own, so that a press never waits for the console process.

Through the console app, a press (`POST /api/estop`) waited for the app's event loop to be scheduled, in one
process whose interpreter lock the control loop, the video writer and the policy link share: under load (load
average 12 plus 4 busy processes on the 2-core machine) press to hold on the bus took p99 109 ms. This process
does nothing but wait for a press, on a listening socket and a connection to the arms of its own: the same
`PiperDriver` (the maker's piper-sdk) on the same CAN buses, a second socket on each SocketCAN port on hardware,
the `dojo_host` buses in the emulator (`dojo.backends.real.host_can`). It connects without enabling anything
(`connect(enable=False)`) and only listens until a press.

A press is `POST /estop` with the operator's token (bearer header, or the console's login cookie, which the
browser sends to this port of the same host; anything else answers 401). It raises the halt flag it shares with
the console's safety layer (`SafetyLayer.remote_halt`: every command not yet sent is refused from then on), holds
the arms (their measured joints, through the driver), answers, and tells the console, whose listener calls the
session's e-stop: the safety layer holds again, behind any command that was being sent, and begins the slow
return to the reset pose. The console page sends its E-stop button and Escape key here (its port is in the live
state), and to the app's `/api/estop` if this process does not answer; that path stays for a robot this process
cannot reach (one without a CAN bus, as the emulated ARX X5).
"""

from __future__ import annotations

import json
import multiprocessing
import os
import secrets
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from http.cookies import SimpleCookie
from http.server import BaseHTTPRequestHandler, HTTPServer
from typing import Any

from dojo.backends.real.piper_driver import PiperDriver

START_TIMEOUT_S = 60.0
"""Longest the console waits for the process to import, connect to the arms and listen."""


class EstopProcess:
    """The e-stop process for the arms `driver` speaks to (see the module docstring), listening on host:port
    (port 0: any free one, then `port`); `on_press(time)` runs in the console process after each press."""

    def __init__(self, driver: PiperDriver, token: str, cookie: str, host: str, port: int,
                 on_press: Callable[[float], None]) -> None:
        context = multiprocessing.get_context("spawn")  # the console has threads: never fork it
        self.halt = context.Value("b", 0, lock=False)
        ready, ready_in = context.Pipe(duplex=False)
        self._presses, presses_in = context.Pipe(duplex=False)
        lifeline, self._lifeline = context.Pipe(duplex=False)  # the process ends when this end closes
        self._process = context.Process(
            target=_serve, name="dojo-console-estop", daemon=True,
            args=(driver.robot, driver.channels, driver.interface, token, cookie, host, port, self.halt, ready_in,
                  presses_in, lifeline))
        self._process.start()
        for end in (ready_in, presses_in, lifeline):
            end.close()
        if not ready.poll(START_TIMEOUT_S):
            self._process.terminate()
            raise TimeoutError(f"the console's e-stop process did not start in {START_TIMEOUT_S} s")
        answer = ready.recv()
        if isinstance(answer, str):
            self._process.join()
            raise RuntimeError(f"the console's e-stop process failed: {answer}")
        self.port: int = answer
        self._on_press = on_press
        self._listener = threading.Thread(target=self._listen, name="dojo-console-estop-listener", daemon=True)
        self._listener.start()

    def _listen(self) -> None:
        while True:
            try:
                pressed = self._presses.recv()
            except (EOFError, OSError):  # the process has ended
                return
            self._on_press(pressed)

    def close(self) -> None:
        self._process.terminate()
        self._process.join(timeout=10)
        self._presses.close()
        self._lifeline.close()


def _serve(robot: Mapping[str, Any], channels: Sequence[str], interface: str, token: str, cookie: str, host: str,
           port: int, halt: Any, ready: Any, presses: Any, lifeline: Any) -> None:
    """The process: connect to the arms, listen, and answer presses until terminated, or until the console's
    process has gone (killed, it cannot terminate this one: the end of `lifeline` it held closes instead)."""
    threading.Thread(target=_end_with_the_console, args=(lifeline,), daemon=True).start()
    try:
        driver = PiperDriver(robot, channels, interface)
        driver.connect(enable=False)
        server = HTTPServer((host, port), _press_handler(driver, token, cookie, halt, presses))
    except Exception as exc:  # said to the console, which raises it
        ready.send(f"{type(exc).__name__}: {exc}")
        return
    ready.send(server.server_address[1])
    server.serve_forever()


def _end_with_the_console(lifeline: Any) -> None:
    try:
        lifeline.recv()
    except (EOFError, OSError):
        pass
    os._exit(0)


def _press_handler(driver: PiperDriver, token: str, cookie: str, halt: Any, presses: Any) -> type:
    class Press(BaseHTTPRequestHandler):
        def do_POST(self) -> None:  # noqa: N802 (the stdlib's name)
            if self.path != "/estop":
                self._answer(404, {"detail": "POST /estop"})
                return
            if not _authorised(self.headers, token, cookie):
                self._answer(401, {"detail": "the console's token is needed"})
                return
            halted = time.monotonic()
            halt.value = 1
            driver.hold()
            held = time.monotonic()
            self._answer(200, {"halted_at": halted, "held_at": held})  # monotonic: the machine's one clock
            try:
                presses.send(held)
            except OSError:  # the console has gone; the arms hold
                pass

        def _answer(self, status: int, body: dict[str, Any]) -> None:
            data = json.dumps(body).encode()
            self.send_response(status)
            origin = self.headers.get("Origin")
            if origin:  # the console page, on another port of this host, may read the answer
                self.send_header("Access-Control-Allow-Origin", origin)
                self.send_header("Access-Control-Allow-Credentials", "true")
                self.send_header("Vary", "Origin")
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)

        def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 (the stdlib's name)
            """Quiet: the console prints nothing per request either."""

    return Press


def _authorised(headers: Any, token: str, cookie: str) -> bool:
    """The operator's token as a bearer header or in the console's login cookie."""
    given = [headers.get("Authorization", "").removeprefix("Bearer ").strip()]
    jar = SimpleCookie(headers.get("Cookie", ""))
    if cookie in jar:
        given.append(jar[cookie].value)
    return any(g and secrets.compare_digest(g.encode(), token.encode()) for g in given)
