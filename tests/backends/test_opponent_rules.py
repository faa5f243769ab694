"""The opponent's named rules on hand-built tic-tac-toe boards (cells 0-8 row by row): `win_then_block` wins when
one move does, else blocks the robot's line, else follows its preference; `random` takes the first free cell of
its drawn order. The last test runs the rule inside the actor on the CPU backend: it blocks the robot's row."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from dojo.backends.mujoco.backend import MujocoBackend
from dojo.backends.opponent_rules import RULES, win_then_block
from dojo.compiler.plan import Plan, compile_plan
from dojo.compiler.spec_library import SpecLibrary

LINES = [[0, 1, 2], [3, 4, 5], [6, 7, 8], [0, 3, 6], [1, 4, 7], [2, 5, 8], [0, 4, 8], [2, 4, 6]]
CENTRE_CORNERS_EDGES = [4, 0, 2, 6, 8, 1, 3, 5, 7]


def test_it_completes_its_own_line_before_blocking():
    # own: 0, 1 (2 wins); robot: 3, 4 (5 blocks): winning comes first
    assert win_then_block(CENTRE_CORNERS_EDGES, LINES, own={0, 1}, robot={3, 4}) == 2


def test_it_blocks_the_robots_line():
    assert win_then_block(CENTRE_CORNERS_EDGES, LINES, own={2}, robot={4, 8}) == 0  # diagonal 0-4-8
    assert win_then_block(CENTRE_CORNERS_EDGES, LINES, own={4}, robot={0, 6}) == 3  # column 0-3-6


def test_a_line_with_the_other_players_piece_is_neither_won_nor_blocked():
    # robot holds 0 and 2 of the top row but the opponent holds 1; nothing else threatens: its preference
    assert win_then_block(CENTRE_CORNERS_EDGES, LINES, own={1}, robot={0, 2}) == 4


def test_among_several_wins_or_blocks_the_first_preferred():
    # robot threatens 2 (row 0-1-2) and 6 (column 0-3-6); preference has 2 before 6
    assert win_then_block(CENTRE_CORNERS_EDGES, LINES, own={4}, robot={0, 1, 3}) == 2
    assert win_then_block([6, 2, 4, 0, 8, 1, 3, 5, 7], LINES, own={4}, robot={0, 1, 3}) == 6


def test_without_a_threat_it_follows_its_preference():
    assert win_then_block(CENTRE_CORNERS_EDGES, LINES, own=set(), robot=set()) == 4
    assert win_then_block(CENTRE_CORNERS_EDGES, LINES, own=set(), robot={4}) == 0
    assert win_then_block(CENTRE_CORNERS_EDGES, LINES, own=set(range(5)), robot=set(range(5, 9))) is None


def test_random_takes_the_first_free_cell_of_its_order():
    order = [7, 3, 0, 8, 1, 2, 4, 5, 6]
    assert RULES["random"](order, LINES, {7}, {3}) == 0  # lines are ignored: no win or block
    assert RULES["random"](order, LINES, {0, 1}, {7, 3}) == 8


@pytest.fixture(scope="module")
def blocking_plan() -> Plan:
    library = SpecLibrary.load(strict=False)
    plan = compile_plan(library, library.get("task", "play_tic_tac_toe"), "standard", 0)
    (spec,) = [a["opponent"] for a in plan.program["actors"]]
    cells = spec["cells"]
    rows = [[cells[k] for k in line] for line in LINES]
    fixed = {**spec, "rule": "win_then_block", "lines": rows, "order": [cells[k] for k in CENTRE_CORNERS_EDGES]}
    return dataclasses.replace(plan, program={**plan.program, "actors": [{"opponent": fixed}]})


def test_the_actor_blocks_the_robots_row(blocking_plan):
    plan = blocking_plan
    model = plan.model()
    spec = plan.program["actors"][0]["opponent"]
    noughts = sorted(n for n in plan.objects if plan.objects[n]["group"] == "noughts")
    with MujocoBackend(num_threads=1) as backend:
        backend.load([plan])
        backend.reset()
        data = backend._slots[0].data
        site = lambda cell: data.site_xpos[model.site(plan.objects["board"]["sites"][cell]).id]  # noqa: E731
        # the robot takes cell_1, the opponent the centre; the robot takes cell_4: the opponent blocks the column
        # at cell_7, where its preference alone would take the corner cell_3
        for k, cell in enumerate(["cell_1", "cell_4"]):
            joint = model.joint(f"cross_{k}/free")
            data.qpos[joint.qposadr[0]:joint.qposadr[0] + 3] = [*site(cell)[:2], site(cell)[2] + 0.0005]
            data.qvel[joint.dofadr[0]:joint.dofadr[0] + 6] = 0.0
            for _ in range(spec["delay"] + 5):
                backend.step(np.zeros((1, 14)), mode="delta_joint")
            answer = data.qpos[model.joint(f"{noughts[k]}/free").qposadr[0]:][:2]
            expected = "cell_5" if k == 0 else "cell_7"
            assert np.allclose(answer, site(expected)[:2], atol=0.01), (k, answer)
