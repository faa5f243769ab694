"""Plans for the expert tests: the first scene seeds of every built-in evaluated task, compiled once per session.

They go to `$DOJO_PLAN_CACHE/validity` when that variable is set (a CI cache, or the slow run reusing the plans
`python -m dojo.experts.validity` compiled), else to a session temporary folder.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from dojo.compiler.spec_library import SpecLibrary


@pytest.fixture(scope="session")
def library() -> SpecLibrary:
    return SpecLibrary.load([])


@pytest.fixture(scope="session")
def plan_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cache = os.environ.get("DOJO_PLAN_CACHE")
    return Path(cache) / "validity" if cache else tmp_path_factory.mktemp("validity-plans")
