"""The opponent actor on the CPU backend (play_tic_tac_toe's): it answers each of the robot's pieces settled on
the board, after its delay, with one of its own on the first free cell of its drawn preference order, and never
moves before the robot or onto a taken cell."""

from __future__ import annotations

import numpy as np
import pytest
from dojo.backends.mujoco.backend import MujocoBackend
from dojo.compiler.plan import Plan, compile_plan
from dojo.compiler.spec_library import SpecLibrary


@pytest.fixture(scope="module")
def ttt_plan() -> Plan:
    library = SpecLibrary.load(strict=False)
    return compile_plan(library, library.get("task", "play_tic_tac_toe"), "standard", 0)


def _cell_xy(plan: Plan, cell: str) -> np.ndarray:
    data = plan.initial_data()
    return data.site_xpos[plan.model().site(plan.objects["board"]["sites"][cell]).id][:2].copy()


def test_the_opponent_answers_each_move_on_its_first_free_cell(ttt_plan):
    plan = ttt_plan
    opponent = plan.program["actors"][0]["opponent"]
    order = opponent["order"]
    assert sorted(order) == sorted(opponent["cells"]) and "actors" in plan.requires
    model = plan.model()
    noughts = sorted(n for n in plan.objects if plan.objects[n]["group"] == "noughts")

    def xy(data, name):
        adr = model.joint(f"{name}/free").qposadr[0]
        return data.qpos[adr:adr + 2].copy()

    with MujocoBackend(num_threads=1) as backend:
        backend.load([plan])
        backend.reset()
        data = backend._slots[0].data
        start = {n: xy(data, n) for n in noughts}
        for _ in range(40):  # no move of the robot: no answer
            backend.step(np.zeros((1, 14)), mode="delta_joint")
        assert all(np.allclose(xy(data, n), start[n], atol=1e-3) for n in noughts)
        board_z = data.site_xpos[model.site(plan.objects["board"]["sites"]["cell_1"]).id][2]
        for k, cell in enumerate([order[0], order[2]]):  # the robot takes the opponent's favourite cell first
            adr = model.joint(f"cross_{k}/free").qposadr[0]
            data.qpos[adr:adr + 3] = [*_cell_xy(plan, cell), board_z + 0.0005]
            data.qvel[model.joint(f"cross_{k}/free").dofadr[0]:][:6] = 0.0
            for _ in range(opponent["delay"] + 5):
                backend.step(np.zeros((1, 14)), mode="delta_joint")
            answer = xy(data, noughts[k])
            expected = order[1] if k == 0 else order[3]  # its first free cell: order[0], order[2] are taken
            assert np.allclose(answer, _cell_xy(plan, expected), atol=0.01), (k, answer)
            assert all(np.allclose(xy(data, n), start[n], atol=1e-3) for n in noughts[k + 1:])  # one answer a move
