"""The console's e-stop process (`dojo.realeval.estop`) and the shared CAN buses it reaches the emulator through
(`dojo.backends.real.host_can`): a press with the operator's token holds the emulated arms through the process's
own piper-sdk connection, refuses the policy's commands from then on and tells the console; without the token it
answers 401 and nothing moves. The slow test measures HTTP press to the hold on the bus under load.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

can = pytest.importorskip("can")
pytest.importorskip("piper_sdk")
httpx = pytest.importorskip("httpx")

from dojo.backends.real.piper_driver import PiperDriver  # noqa: E402
from dojo.backends.real.safety import SafetyLayer  # noqa: E402
from dojo.realeval.estop import EstopProcess  # noqa: E402
from safety_rig import commanding_away, latency_summary, rig_safety  # noqa: E402

TOKEN = "estop-test-token"
COOKIE = "dojo_console"
CLIENT = """
import json, sys, time
import httpx
import numpy as np
url, token, presses = sys.argv[1], sys.argv[2], int(sys.argv[3])
rng = np.random.default_rng(0)
with httpx.Client() as client:
    for _ in range(presses):
        time.sleep(rng.uniform(0.25, 0.4))
        pressed = time.monotonic()
        answer = client.post(url, headers={"Authorization": "Bearer " + token}).json()
        print(json.dumps({"pressed": pressed, **answer}), flush=True)
"""


def test_channels_of_the_shared_bus_are_separate_and_reach_other_processes() -> None:
    left, right = (can.Bus(interface="dojo_host", channel=f"dojo-test-{os.getpid()}-{side}") for side in "lr")
    child = subprocess.Popen([sys.executable, "-c", (
        "import can; b = can.Bus(interface='dojo_host', channel='dojo-test-%d-l'); m = b.recv(10); "
        "b.send(can.Message(arbitration_id=m.arbitration_id + 1, data=m.data, is_extended_id=False)); b.shutdown()"
    ) % os.getpid()])
    try:
        deadline, answer = time.monotonic() + 30, None
        while answer is None and time.monotonic() < deadline:  # until the child listens
            left.send(can.Message(arbitration_id=0x155, data=b"\x01\x02", is_extended_id=False))
            answer = left.recv(0.2)
        assert answer is not None and answer.arbitration_id == 0x156 and bytes(answer.data) == b"\x01\x02"
        assert right.recv(0.1) is None  # the other arm's bus heard nothing, and no bus hears itself
    finally:
        child.wait(10)
        left.shutdown()
        right.shutdown()


@pytest.fixture
def armed(make_rig):
    """The emulated PiPER on shared buses, driven from this process through the safety layer at 25 Hz towards a
    pose away from home (the console's part), and the e-stop process on the same buses."""
    rig = make_rig(bus="dojo_host")
    with PiperDriver(rig.robot, rig.channels, interface="dojo_host") as driver:
        driver.connect()
        safety = rig_safety(rig, driver)
        told: list[float] = []
        process = EstopProcess(driver, TOKEN, COOKIE, "127.0.0.1", 0,
                               on_press=lambda at: (told.append(at), safety.estop()))
        safety.remote_halt = process.halt
        try:
            with commanding_away(safety):
                yield rig, safety, process, told
        finally:
            process.close()
            safety.close()


def test_a_press_holds_through_the_process_and_the_console_is_told(armed) -> None:
    rig, safety, process, told = armed
    url = f"http://127.0.0.1:{process.port}/estop"
    time.sleep(0.3)
    for headers in ({}, {"Authorization": "Bearer wrong"}, {"Cookie": f"{COOKIE}=wrong"}):
        assert httpx.post(url, headers=headers).status_code == 401
    assert safety.state == "running" and not safety.halted
    answer = httpx.post(url, cookies={COOKIE: TOKEN})  # the browser's way: the console's login cookie
    assert answer.status_code == 200
    halted_at = answer.json()["halted_at"]
    assert process.halt.value == 1 and safety.halted
    deadline = time.monotonic() + 10
    while not _sent_since(rig, halted_at) and time.monotonic() < deadline:
        time.sleep(0.001)
    assert _sent_since(rig, halted_at), "no hold frame reached the emulated arms"
    while not told and time.monotonic() < deadline:
        time.sleep(0.001)
    assert told and safety.estop_time is not None
    held = rig.sim.arm_joints()
    time.sleep(0.1)  # within the e-stop's hold, before the return: the arms stay where they were held
    assert np.abs(rig.sim.arm_joints() - held).max() < 0.01
    assert safety.command(*safety.driver.home_pose).refused == "refused_estop"
    safety.release()
    assert process.halt.value == 0 and not safety.halted


@pytest.mark.slow
@pytest.mark.parametrize("path", ["own_process", "event_loop"])
def test_press_to_hold_on_the_bus_with_the_machine_loaded(armed, figures, path) -> None:
    """The e-stop bar's figure: busy loops in 2 x cores other processes, two pure-Python threads keeping this (the
    console's) process's interpreter lock busy beside the 25 Hz policy; PRESSES HTTP presses from a client
    process, each released after a moment. Per press, from the client's time stamp before its request: the first
    command frame on the arms' bus at or after the halt (its bus time stamp). `own_process`: the e-stop process;
    `event_loop`, for comparison: an endpoint on an event loop in this process calling the safety layer's
    e-stop, as the console app's `/api/estop` does."""
    rig, safety, process, told = armed
    url = f"http://127.0.0.1:{process.port}/estop" if path == "own_process" else _event_loop_endpoint(safety)
    presses = 60
    busy = threading.Event()

    def hog() -> None:  # the console's own Python work (video, policy link), holding the GIL
        while not busy.is_set():
            sum(range(10_000))

    hogs = [threading.Thread(target=hog) for _ in range(2)]
    load = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2 * (os.cpu_count() or 1))]
    latencies, held = [], []
    for thread in hogs:
        thread.start()
    try:
        client = subprocess.Popen([sys.executable, "-c", CLIENT, url, TOKEN, str(presses)], stdout=subprocess.PIPE,
                                  text=True)
        for line in client.stdout:
            press = json.loads(line)
            deadline = time.monotonic() + 10
            while not (sent := _sent_since(rig, press["halted_at"])) and time.monotonic() < deadline:
                time.sleep(0.0005)
            latencies.append(min(sent) - press["pressed"])
            held.append(press["held_at"] - press["pressed"])
            while safety.estop_time is None and time.monotonic() < deadline:  # the console was told
                time.sleep(0.0005)
            time.sleep(0.05)
            safety.release()
        assert client.wait(60) == 0
    finally:
        busy.set()
        for thread in hogs:
            thread.join()
        for p in load:
            p.kill()
            p.wait()

    busy_n = 2 * (os.cpu_count() or 1)
    figures.add(f"estop.{path}.press_to_hold_on_the_bus_ms({busy_n} busy processes; HTTP press -> first frame)",
                latency_summary(latencies))
    figures.add(f"estop.{path}.press_to_hold_sent_ms(HTTP press -> the hold sent)", latency_summary(held))
    assert len(latencies) == presses


def _event_loop_endpoint(safety: SafetyLayer) -> str:
    """`POST /estop` on a uvicorn event loop in this process, calling `safety.estop()` on the loop as the console
    app's `/api/estop` does (the server thread lives until the test process ends)."""
    uvicorn = pytest.importorskip("uvicorn")
    from fastapi import FastAPI

    app = FastAPI()

    @app.post("/estop")
    async def estop() -> dict[str, float]:
        halted = safety.estop()
        return {"halted_at": halted, "held_at": time.monotonic()}

    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=0, log_level="warning"))
    threading.Thread(target=server.run, daemon=True).start()
    deadline = time.monotonic() + 30
    while not server.started and time.monotonic() < deadline:
        time.sleep(0.05)
    port = server.servers[0].sockets[0].getsockname()[1]
    return f"http://127.0.0.1:{port}/estop"


def _sent_since(rig, t: float) -> list[float]:
    """Bus time stamps of the command frames put on the arms' buses at or after `t` (the emulator logs each when
    its thread reads it, later)."""
    return [f.on_bus for f in rig.emulator.frames_since(t) if f.on_bus >= t]
