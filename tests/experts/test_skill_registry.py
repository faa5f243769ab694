"""The skill registry: one home per skill word. A skill added in this one file is accepted by the task schema and
drives the oracle to success on a real plan; the schema file and the registry agree."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from dojo.compiler.spec_library import SpecLibrary
from dojo.compiler.spec_schema import schema_dir
from dojo.language import skills
from dojo.experts.skills import push_up
from dojo.experts.validity import plan_files, run_policy
from dojo.experts.oracle import OraclePolicy

TEST_PACK = Path(__file__).parents[1] / "specs" / "pack"
TASK = """kind: task
version: 1
id: raise_block_test
dimension: generalization
embodiment: arx_x5_bimanual
instruction: Raise the block and hold it up.
settings:
  standard: {clutter: [0, 0]}
  random: {clutter: [0, 0]}
scene:
  regions:
    left: {center: [-0.2, 0.0], size: [0.2, 0.2]}
  objects:
    - {name: block, asset: {category: test_block}, region: left}
success: {lifted: [block, 0.08]}
expert:
  - {skill: raise_and_hold, object: block, height: 0.15, steps: 10}
horizon: 200
"""


def run_raise_and_hold(ctx, step):
    """Lift the object to `height` above the table, then hold it there for `steps` control steps."""
    yield from push_up(ctx, step.get("arm", "auto"), step["object"], float(step["height"]))
    yield ctx.hold(int(step.get("steps", 10)))


@pytest.fixture
def raise_and_hold():
    word = skills.register(skills.SkillWord("raise_and_hold", "lift the object and hold it up", run_raise_and_hold))
    yield word
    skills.unregister("raise_and_hold")


@pytest.fixture
def pack(tmp_path: Path) -> Path:
    shutil.copytree(TEST_PACK / "assets", tmp_path / "assets")
    (tmp_path / "tasks").mkdir()
    (tmp_path / "tasks" / "raise_block_test.yaml").write_text(TASK)
    return tmp_path


def test_the_schema_file_lists_exactly_the_registered_skills():
    schema = json.loads((schema_dir() / "task.schema.json").read_text())
    assert schema["$defs"]["skill"]["properties"]["skill"] == skills.schema_property(), \
        "specs/schemas/task.schema.json and dojo.language.skills disagree: update the file from the registry"


def test_every_built_in_skill_has_a_runner():
    for name in skills.names():
        assert callable(skills.word(name).runner()), name


def test_an_unregistered_skill_is_a_located_schema_error(pack):
    problems = [str(p) for p in SpecLibrary.load([pack], strict=False).problems]
    assert any("raise_block_test.yaml:17:" in p and "$.expert[0].skill" in p and "is not one of" in p
               for p in problems), problems


def test_a_new_skill_is_accepted_and_drives_the_oracle(pack, raise_and_hold, tmp_path_factory):
    library = SpecLibrary.load([pack])
    files = plan_files(library, ["raise_block_test"], 1, tmp_path_factory.mktemp("plans"))
    outcomes = run_policy(OraclePolicy({"packs": [str(pack)]}), files["raise_block_test"], num_envs=1, threads=1)
    assert [o.success for o in outcomes] == [True], outcomes
