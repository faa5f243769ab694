"""The taxonomy as data: RoboDojo's dimensions come from a spec, a pack adds its own (scored, split into settings
or not), and a task's dimension is checked against it with a located error."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from dojo.compiler.spec_library import SpecLibrary
from dojo.compiler.suite_compile import suite_episodes
from dojo.compiler.taxonomy import builtin_taxonomy, taxonomy_of
from dojo.report.scoring import score_episodes

PACK = Path(__file__).parents[1] / "specs" / "pack"
TAXONOMY = """kind: taxonomy
version: 1
id: my_lab
dimensions:
  - {id: dexterity, label: Dexterity, compare_settings: [standard, random]}
"""


def test_robodojo_taxonomy():
    taxonomy = builtin_taxonomy()
    assert taxonomy.scored == ("generalization", "precision", "long_horizon", "memory", "open")
    assert taxonomy.training_only == ("dlc",) and taxonomy.evaluation_only == ("open",)
    assert taxonomy.compare_settings("generalization") == ("standard", "random")
    assert taxonomy.compare_settings("memory") == () and taxonomy.label("long_horizon") == "Long-Horizon"


@pytest.fixture
def pack(tmp_path: Path) -> Path:
    shutil.copytree(PACK, tmp_path / "pack")
    return tmp_path / "pack"


def test_a_pack_adds_a_dimension_that_suites_split_and_scoring_counts(pack, make_task_rows):
    (pack / "my_lab.yaml").write_text(TAXONOMY)
    task = pack / "tasks" / "stack_test.yaml"
    task.write_text(task.read_text().replace("dimension: generalization", "dimension: dexterity"))
    library = SpecLibrary.load([pack])
    taxonomy = taxonomy_of(library)
    assert taxonomy.ids[-1] == "dexterity" and "dexterity" in taxonomy.scored
    suite = library.get("suite", "mini_test")
    settings = {e.setting for e in suite_episodes(library, suite, episodes=4) if e.task == "stack_test"}
    assert settings == {"standard", "random"}
    rows = make_task_rows("stack_test", "dexterity", [(True, 100.0), (False, 50.0)])
    scores = score_episodes(rows, taxonomy=taxonomy)
    assert list(scores.dimensions) == ["dexterity"] and scores.overall.score.mean == 75.0


def test_an_unknown_dimension_is_a_located_error_with_a_suggestion(pack):
    task = pack / "tasks" / "stack_test.yaml"
    text = task.read_text().replace("dimension: generalization", "dimension: generalisation")
    task.write_text(text)
    problems = [str(p) for p in SpecLibrary.load([pack], strict=False).problems]
    line = text.splitlines().index("dimension: generalisation") + 1
    assert any(f"stack_test.yaml:{line}:" in p and "unknown dimension 'generalisation'" in p and "generalization" in p
               for p in problems), problems


def test_a_pack_may_not_redefine_a_dimension(pack):
    (pack / "my_lab.yaml").write_text(TAXONOMY.replace("dexterity, label: Dexterity", "memory, label: Recall"))
    problems = [str(p) for p in SpecLibrary.load([pack], strict=False).problems]
    assert any("my_lab.yaml" in p and "dimension 'memory' is defined already" in p for p in problems), problems
