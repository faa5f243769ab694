"""Plans for the backend tests: the test pack's stack task and this folder's probe task (button, bin, group).

Plans are compiled once per session. The library is loaded non-strictly so that a half-written built-in spec
elsewhere in the tree does not break these tests; the specs used here are checked to be valid.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from dojo.compiler.plan import Plan, compile_plan
from dojo.compiler.spec_library import SpecLibrary

HERE = Path(__file__).parent
PACKS = [HERE.parent / "specs" / "pack", HERE / "pack"]


@pytest.fixture(scope="session")
def library() -> SpecLibrary:
    lib = SpecLibrary.load(PACKS, strict=False)
    mine = [p for p in lib.problems if "tests/" in str(p)]
    assert not mine, mine
    return lib


@pytest.fixture(scope="session")
def stack_plan(library: SpecLibrary) -> Plan:
    """stack_test: a 4 cm block (left) to put on a plate (right); stages lifted (w 1), placed (w 2)."""
    return compile_plan(library, library.get("task", "stack_test"), "standard", 0)


@pytest.fixture(scope="session")
def probe_plan(library: SpecLibrary) -> Plan:
    """probe_predicates: cubes cube_0, cube_1 (group cubes), fixed bin with an inside box, push button."""
    return compile_plan(library, library.get("task", "probe_predicates"), "standard", 0)


def _set_free_pose(plan: Plan, qpos: np.ndarray, body: str, pos, quat=(1.0, 0.0, 0.0, 0.0)) -> None:
    adr = plan.model().joint(f"{body}/free").qposadr[0]
    qpos[adr:adr + 3] = pos
    qpos[adr + 3:adr + 7] = quat


@pytest.fixture
def set_free_pose():
    """`set_free_pose(plan, qpos, body, pos, quat=...)` writes a free body's pose into a qpos vector of `plan`'s
    model (to build states by hand)."""
    return _set_free_pose
