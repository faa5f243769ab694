"""The strict audit's result cache: a record is reused only for the same plan hash and the same code."""

from __future__ import annotations

import json
from pathlib import Path

from dojo.strict.work import EpisodeRecord, ResultCache, code_fingerprint


def test_a_record_is_reused_by_the_same_code_only(tmp_path: Path) -> None:
    record = EpisodeRecord("expert", "standard", 3, True, 100.0, 250)
    old = ResultCache(tmp_path, code="old")
    old.put("h1", "expert", record)
    assert old.get("h1", "expert")["steps"] == 250 and old.get("h1", "zero") is None
    new = ResultCache(tmp_path, code="new")
    assert new.get("h1", "expert") is None  # a skill changed: the episode is run again
    new.put("h1", "expert", record)
    assert list(json.loads((tmp_path / "h1.json").read_text())) == ["expert@new"]  # the old code's record is gone


def test_the_fingerprint_follows_every_source_file(tmp_path: Path) -> None:
    (tmp_path / "experts").mkdir()
    skill = tmp_path / "experts" / "skills.py"
    skill.write_text("LIFT = 0.10\n")
    (tmp_path / "notes.txt").write_text("not code")
    before = code_fingerprint(tmp_path)
    (tmp_path / "notes.txt").write_text("still not code")
    assert code_fingerprint(tmp_path) == before
    skill.write_text("LIFT = 0.12\n")
    assert code_fingerprint(tmp_path) != before
    assert len(code_fingerprint()) == 16  # the installed package
