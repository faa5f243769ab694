"""Hidden verification layouts through `dojo run`: a private seed set, evaluated beside the public one."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

from dojo.evaluation.results_store import ResultsStore

PACK = Path(__file__).resolve().parents[1] / "specs" / "pack"


def test_hidden_seed_set_is_evaluated_and_verified(tmp_path: Path) -> None:
    pack = tmp_path / "pack"
    shutil.copytree(PACK, pack)
    suite = pack / "suites" / "mini_test.yaml"
    suite.write_text(suite.read_text() + "verification: {seed_set: lab_secret, episodes: 2}\n")
    secrets = tmp_path / "secrets.json"
    secrets.write_text(json.dumps({"lab_secret": [911]}))
    env = dict(os.environ, DOJO_PLAN_CACHE=str(tmp_path / "plans"))
    result = subprocess.run(
        [sys.executable, "-m", "dojo.cli.main", "run", f"packs=[{pack}]", "suite=mini_test", "episodes=1",
         "seeds=[0]", "num_envs=2", "progress=quiet", f"hidden_seeds={secrets}", f"results={tmp_path / 'r.sqlite'}",
         f"report={tmp_path / 'report.json'}"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    with ResultsStore(tmp_path / "r.sqlite", readonly=True) as store:
        rows = store.rows()
    assert sorted(r.split for r in rows) == ["hidden", "hidden", "public"]
    assert {r.eval_seed for r in rows if r.split == "hidden"} == {911}
    report = json.loads((tmp_path / "report.json").read_text())
    text = json.dumps(report)
    assert "verif" in text  # the report carries the verdict of the two-proportion test
    for row in rows:  # hidden layouts stay private: their plan hashes never reach the report
        if row.split == "hidden":
            assert row.plan_hash not in text
