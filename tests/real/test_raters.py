"""Raters' credentials: issued once, stored only as hashes, revocable, read again by a running console, and a
broken raters file is reported with its path and line."""

from __future__ import annotations

import hashlib
import json
import re
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from dojo.realeval.raters import RaterRegistry


def test_a_rater_token_identifies_its_rater_and_only_its_hash_is_stored(tmp_path: Path) -> None:
    path = tmp_path / "raters.json"
    raters = RaterRegistry(path)
    alice, bob = raters.add("alice"), raters.add("bob")
    assert alice != bob and raters.identify(alice) == "alice" and raters.identify(bob) == "bob"
    assert raters.identify("not-a-token") is None and raters.identify(alice + "x") is None
    text = path.read_text()
    assert alice not in text and bob not in text
    assert json.loads(text)["raters"]["alice"] == hashlib.sha256(alice.encode()).hexdigest()
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    with pytest.raises(ValueError, match="already has a token"):
        raters.add("alice")
    with pytest.raises(ValueError, match="rater name"):
        raters.add("../evil")


def test_a_running_console_sees_raters_added_and_removed_elsewhere(tmp_path: Path) -> None:
    path = tmp_path / "raters.json"
    console_view = RaterRegistry(path)
    assert console_view.identify("anything") is None  # no file yet: no raters
    token = RaterRegistry(path).add("carol")
    assert console_view.identify(token) == "carol"
    RaterRegistry(path).remove("carol")
    assert console_view.identify(token) is None
    with pytest.raises(KeyError, match="no rater 'carol'"):
        console_view.remove("carol")


def test_a_broken_raters_file_names_the_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "raters.json"
    path.write_text('{\n "raters": {"alice": \n')
    with pytest.raises(ValueError, match=rf"{re.escape(str(path))}: line 3: not JSON"):
        RaterRegistry(path).identify("x")
    path.write_text('{"raters": {"alice": "plaintext-token"}}')
    with pytest.raises(ValueError, match="field 'raters' must map rater names to SHA-256"):
        RaterRegistry(path).names()


def test_dojo_console_add_rater_prints_the_token_once_and_remove_rater_revokes_it(tmp_path: Path) -> None:
    path = tmp_path / "raters.json"

    def dojo(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "dojo.cli.main", "console", *args, f"raters={path}"],
                              capture_output=True, text=True, timeout=120)

    added = dojo("add-rater", "dana")
    assert added.returncode == 0, added.stderr
    token = added.stdout.strip().rsplit(" ", 1)[-1]
    assert RaterRegistry(path).identify(token) == "dana"
    again = dojo("add-rater", "dana")
    assert again.returncode == 1 and "already has a token" in again.stderr
    assert dojo("remove-rater", "dana").returncode == 0
    assert RaterRegistry(path).identify(token) is None
