"""What the safety and e-stop tests share: a safety layer on an emulator rig, a 25 Hz policy thread commanding both
arms away from home through it (what the e-stop interrupts), and the latency summary their figures report."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
from dojo.backends.real.safety import SafetyLayer
from dojo.backends.real.workspace import RobotGeometry

CONTROL_HZ = 25.0
AWAY = np.array([[0.4, 0.2, -0.2, 0.3, 0.2, 0.5], [-0.4, 0.2, -0.2, -0.3, 0.2, -0.5]])
"""Joint offsets from home (rad, per arm) the policy thread commands: far enough that holding and returning show."""


def rig_safety(rig: Any, driver: Any) -> SafetyLayer:
    """A started safety layer over `driver`, with the rig's robot geometry, settings and emulator clock."""
    safety = SafetyLayer(driver, RobotGeometry(rig.model, rig.robot), rig.config, CONTROL_HZ, clock=rig.sim.clock)
    safety.start()
    return safety


@contextmanager
def commanding_away(safety: SafetyLayer) -> Iterator[np.ndarray]:
    """A policy thread sending home + AWAY through `safety` at CONTROL_HZ until the block ends; yields home."""
    home_q, grip = safety.driver.home_pose
    target = home_q + AWAY
    done = threading.Event()

    def policy() -> None:
        while not done.is_set():
            safety.command(target, grip)
            time.sleep(1.0 / CONTROL_HZ)

    thread = threading.Thread(target=policy)
    thread.start()
    try:
        yield home_q
    finally:
        done.set()
        thread.join()


def latency_summary(seconds: list[float]) -> dict[str, float]:
    """p50, p99 and max in milliseconds, and how many samples."""
    ms = 1000.0 * np.asarray(seconds)
    return {"p50": round(float(np.percentile(ms, 50)), 2), "p99": round(float(np.percentile(ms, 99)), 2),
            "max": round(float(ms.max()), 2), "presses": len(seconds)}
