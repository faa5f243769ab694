"""Settling a sampled scene at compile time, and telling a layout that settles from one that does not.

Sampled objects are dropped a couple of millimetres above their supports, so the compiler simulates the scene
(robot holding home) before it records the initial state. A fixed settling time is not enough: an object that is
still falling or toppling when the clock stops would be frozen mid-fall (its velocity zeroed) and the episode would
start with a tilted object that topples at the first step. So settling runs until every free object is at rest,
up to a bound, and then compares each object with the pose it was sampled in: one that slid, rolled or tipped
over (it landed on a neighbour, or a neighbour knocked it) means the layout is physically wrong, and the compiler
draws another one from the same seed (`scene_sample.sample_scene(..., redraw=k)`).

Loose contents (balls put inside a cup) are judged by where their centre of mass is, not by how they are turned:
a ball rolling into a gap moves its centre, but one perched on two others creeps round at 1 mm/s, turning 0.6
degrees a window, and its turn alone kept a quarter of the layouts of a cup of ten balls moving to the bound.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

MIN_SECONDS = 0.3        # always simulate this long: drops of a few millimetres land within it
MAX_SECONDS = 2.0        # give up waiting for rest after this long (the layout is then rejected)
WINDOW_SECONDS = 0.1     # rest is judged over a window, so that one-step contact chatter does not count as motion
REST_DISPLACEMENT = 1e-3  # m a free body's origin may move within one window and still be at rest (1 cm/s)
REST_TURN_DEG = 0.5      # degrees it may turn within one window (a lying cylinder rolls in place)
MAX_SLIDE = 0.02         # m of horizontal travel from the sampled pose before an object counts as disturbed
MAX_TILT_DEG = 20.0      # degrees an object's up axis may turn from the sampled pose (toppled, rolled)


@dataclass(frozen=True)
class SettleResult:
    """How a scene settled: the simulated time, whether every free object came to rest, and the objects that
    moved away from their sampled pose (name -> what happened), which is empty for a good layout."""

    seconds: float
    at_rest: bool
    disturbed: dict[str, str]

    @property
    def ok(self) -> bool:
        return self.at_rest and not self.disturbed


def settle(model: mujoco.MjModel, data: mujoco.MjData, free_bodies: dict[str, str],
           loose: frozenset[str] = frozenset()) -> SettleResult:
    """Step `data` until the free bodies (object name -> root body name) rest, between MIN_SECONDS and
    MAX_SECONDS; `data` is left at the settled state with velocities zeroed. `loose` objects (contents put
    inside a container, which roll into the gaps of the layer below) may turn while they settle; they must
    still come to rest and not slide away."""
    ids = {name: model.body(body).id for name, body in free_bodies.items()}
    start = _poses(data, ids)
    window = max(1, round(WINDOW_SECONDS / model.opt.timestep))
    min_steps, max_steps = round(MIN_SECONDS / model.opt.timestep), round(MAX_SECONDS / model.opt.timestep)
    steps, at_rest = 0, False
    while not at_rest and steps < max_steps:
        before = _poses(data, ids, loose)
        mujoco.mj_step(model, data, nstep=window)
        steps += window
        moved, turned = _largest_change(before, _poses(data, ids, loose), loose)
        at_rest = steps >= min_steps and moved < REST_DISPLACEMENT and turned < REST_TURN_DEG
    data.qvel[:] = 0.0
    mujoco.mj_forward(model, data)
    disturbed = {}
    for name, (pos, rot) in _poses(data, ids).items():
        slide = float(np.linalg.norm(pos[:2] - start[name][0][:2]))
        tilt = _angle_deg(rot[:, 2], start[name][1][:, 2])
        if slide > MAX_SLIDE or (tilt > MAX_TILT_DEG and name not in loose):
            disturbed[name] = f"moved {slide * 100:.1f} cm, turned {tilt:.0f} deg"
    return SettleResult(seconds=steps * model.opt.timestep, at_rest=at_rest, disturbed=disturbed)


def _poses(data: mujoco.MjData, ids: dict[str, int],
           loose: frozenset[str] = frozenset()) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each body's position and rotation; a loose body's position is its centre of mass (a ball's frame origin
    is on its surface, which swings round as the ball turns in place)."""
    return {name: ((data.xipos if name in loose else data.xpos)[b].copy(), data.xmat[b].reshape(3, 3).copy())
            for name, b in ids.items()}


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


def _largest_change(before: dict[str, tuple[np.ndarray, np.ndarray]],
                    after: dict[str, tuple[np.ndarray, np.ndarray]],
                    loose: frozenset[str] = frozenset()) -> tuple[float, float]:
    """The largest displacement (m) and rotation (degrees) of any body between two snapshots; the rotation of
    loose bodies is left out (their displacement is what says whether they still move)."""
    moved = turned = 0.0
    for name, (pos, rot) in after.items():
        moved = max(moved, float(np.linalg.norm(pos - before[name][0])))
        if name in loose:
            continue
        cos = (np.trace(before[name][1].T @ rot) - 1.0) / 2.0
        turned = max(turned, float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))))
    return moved, turned
