"""Plans for the render tests: stack_blocks seed 0 in the standard and the random setting (built-in specs).

Compiled once per session; the built-in library is loaded non-strictly so that a half-written spec elsewhere in the
tree does not break these tests. The headless GL platform is chosen by tests/conftest.py.
"""

from __future__ import annotations

import pytest
from dojo.compiler.plan import Plan, compile_plan
from dojo.compiler.spec_library import SpecLibrary

TASK = "stack_blocks"


@pytest.fixture(scope="session")
def library() -> SpecLibrary:
    return SpecLibrary.load(strict=False)


@pytest.fixture(scope="session")
def standard_plan(library: SpecLibrary) -> Plan:
    return compile_plan(library, library.get("task", TASK), "standard", 0)


@pytest.fixture(scope="session")
def random_plan(library: SpecLibrary) -> Plan:
    return compile_plan(library, library.get("task", TASK), "random", 0)
