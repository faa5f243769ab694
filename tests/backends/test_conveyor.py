"""The conveyor actor on the CPU backend: items wait out of the scene for their turn (pauses included), enter at the
belt's upstream end, move at the drawn speed, leave at the far end; one lifted off the belt is no longer carried.
Its choices (order of a group, speed from a range) are drawn from the episode's seed, so they are part of the plan."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from dojo.backends.conveyor import PARKED
from dojo.backends.mujoco.backend import MujocoBackend
from dojo.compiler.actor_draws import draw_actors
from dojo.compiler.plan import Plan, compile_plan


@pytest.fixture(scope="module")
def conveyor_plan(library) -> Plan:
    return compile_plan(library, library.get("task", "probe_conveyor"), "standard", 0)


def _pos(plan: Plan, data, name: str) -> np.ndarray:
    adr = plan.model().joint(f"{name}/free").qposadr[0]
    return data.qpos[adr:adr + 3].copy()


def test_choices_are_drawn_per_episode_and_repeat_exactly():
    spec = [{"conveyor": {"belt": "b", "speed": [0.1, 0.2], "items": ["x", 5, ["a", "b", "c", "d"]]}}]
    draws = [draw_actors(spec, "t", "standard", seed)[0]["conveyor"] for seed in range(12)]
    assert draws[3] == draw_actors(spec, "t", "standard", 3)[0]["conveyor"]
    assert all(d["items"][:2] == ["x", 5] and sorted(d["items"][2:]) == ["a", "b", "c", "d"] for d in draws)
    assert len({tuple(d["items"]) for d in draws}) > 1 and len({d["speed"] for d in draws}) == 12
    assert all(0.1 <= d["speed"] <= 0.2 for d in draws)


def test_items_enter_in_turn_ride_and_leave(conveyor_plan):
    plan = conveyor_plan
    conveyor = plan.program["actors"][0]["conveyor"]
    assert "actors" in plan.requires and 0.1 <= conveyor["speed"] <= 0.2
    order = [n for n in conveyor["items"] if isinstance(n, str)]
    enters = dict(zip(order, [2, 17, 27]))  # start 2, then spacing 10 plus the 5-step pause, then spacing 10
    dt = plan.n_substeps * plan.model().opt.timestep
    with MujocoBackend(num_threads=1) as backend:
        backend.load([plan])
        backend.reset()
        data = backend._slots[0].data
        track: dict[str, list[np.ndarray]] = {n: [] for n in order}
        for _ in range(200):
            for name in order:
                track[name].append(_pos(plan, data, name))
            backend.step(np.zeros((1, 14)), mode="delta_joint")
    for name, steps in enters.items():
        xs = np.array([p[0] for p in track[name]])
        assert np.all(xs[:steps] < PARKED[0] + 2.0), name            # waiting: parked far away
        entered = -0.3 + 0.02 * np.sqrt(3) + conveyor["speed"] * dt  # its corner at the upstream end, then one step
        assert xs[steps + 1] == pytest.approx(entered, abs=1e-6), name
        moved = xs[steps + 6] - xs[steps + 1]
        assert moved == pytest.approx(5 * conveyor["speed"] * dt, abs=1e-6), name
    first = np.array([p[0] for p in track[order[0]]])
    assert first[-1] < PARKED[0] + 2.0  # past the far end by now: removed


def test_an_item_lifted_off_the_belt_is_no_longer_carried(conveyor_plan):
    plan = conveyor_plan
    with MujocoBackend(num_threads=1) as backend:
        backend.load([plan])
        backend.reset()
        data = backend._slots[0].data
        for _ in range(5):
            backend.step(np.zeros((1, 14)), mode="delta_joint")
        name = plan.program["actors"][0]["conveyor"]["items"][0]
        adr = plan.model().joint(f"{name}/free").qposadr[0]
        data.qpos[adr + 2] += 0.05  # picked up
        backend.step(np.zeros((1, 14)), mode="delta_joint")
        x = _pos(plan, data, name)[0]
        for _ in range(5):
            backend.step(np.zeros((1, 14)), mode="delta_joint")
        assert _pos(plan, data, name)[0] == pytest.approx(x, abs=1e-3)  # it fell back, and stays where it fell


def test_like_copies_the_drawn_asset_and_draw_from_varies_it(library):
    from dojo.compiler.scene_sample import sample_scene

    spec = library.get("task", "probe_conveyor")
    pool = ["probe_cube", "probe_bin"]
    objects = [{"name": "cue", "asset": "probe_cube", "draw_from": pool, "region": "belt"},
               {"name": "twin", "asset": "probe_cube", "like": "cue", "region": "belt"}]
    task = dataclasses.replace(spec, data={**spec.data, "actors": [], "scene": {**spec.data["scene"],
                                                                                "objects": objects}})
    drawn = set()
    for seed in range(8):
        scene = {o.name: o for o in sample_scene(library, task, "standard", seed).objects}
        assert scene["twin"].asset == scene["cue"].asset and scene["twin"].scale == scene["cue"].scale
        drawn.add(scene["cue"].asset)
    assert drawn == set(pool)


def test_the_first_state_shows_only_what_is_there_at_the_first_step(conveyor_plan):
    from dojo.backends.world_actors import first_state

    data = first_state(conveyor_plan, conveyor_plan.model())
    assert all(_pos(conveyor_plan, data, n)[0] < PARKED[0] + 2.0 for n in ("first", "cube_a", "cube_b"))  # none yet
