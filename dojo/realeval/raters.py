"""Raters' own credentials: one token per rater, kept only as its hash, so a rater's marks carry who made them.

The operator's token runs the robot; a rater's token opens only the rater pages, and the rater id of a rating is
the name its token was issued to (a rater cannot score under another name, and the operator cannot score at
all). `dojo console add-rater NAME` issues a token, prints it once and stores its SHA-256 in the raters file (a
lab-wide JSON file, `<results root>/console/raters.json` unless `raters=` says otherwise); `remove-rater NAME`
revokes it. Tokens are 144 random bits, so a plain hash is as hard to reverse as the token is to guess; the file
is written readable by its owner only. A running console reads the file again when it changes, so raters can be
added or revoked without restarting it.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import secrets
from dataclasses import dataclass
from pathlib import Path

from dojo.evaluation.run_dir import results_root

NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


def default_raters_file() -> Path:
    """Where the lab's raters are kept unless a `raters=` path is given."""
    return results_root() / "console" / "raters.json"


def _digest(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


@dataclass
class RaterRegistry:
    """The raters file at `path` (missing: no raters yet)."""

    path: Path

    def __post_init__(self) -> None:
        self._seen: tuple[int, int] | None = None
        self._hashes: dict[str, str] = {}

    def names(self) -> list[str]:
        return sorted(self._load())

    def identify(self, token: str) -> str | None:
        """The rater `token` was issued to, or None (compared in constant time against every stored hash)."""
        digest = _digest(token)
        found = None
        for name, stored in self._load().items():
            if secrets.compare_digest(digest, stored):
                found = name
        return found

    def add(self, name: str) -> str:
        """Issue a token to a new rater `name`; the token (shown once: only its hash is kept)."""
        if not NAME.match(name):
            raise ValueError(f"{self.path}: rater name {name!r} must be 1-64 letters, digits, '_', '.' or '-', "
                             "starting with a letter or digit")
        hashes = self._load()
        if name in hashes:
            raise ValueError(f"{self.path}: rater {name!r} already has a token; remove-rater {name} first to "
                             "issue a new one")
        token = secrets.token_urlsafe(18)
        self._write({**hashes, name: _digest(token)})
        return token

    def remove(self, name: str) -> None:
        hashes = self._load()
        if name not in hashes:
            raise KeyError(f"{self.path}: no rater {name!r} (raters: {', '.join(sorted(hashes)) or 'none'})")
        del hashes[name]
        self._write(hashes)

    def _load(self) -> dict[str, str]:
        """The stored hashes by name, read again only when the file changed."""
        try:
            stat = self.path.stat()
        except FileNotFoundError:
            self._seen, self._hashes = None, {}
            return {}
        if self._seen != (stat.st_mtime_ns, stat.st_size):
            self._hashes = self._parse(self.path.read_text())
            self._seen = (stat.st_mtime_ns, stat.st_size)
        return dict(self._hashes)

    def _parse(self, text: str) -> dict[str, str]:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{self.path}: line {exc.lineno}: not JSON ({exc.msg})") from exc
        raters = data.get("raters") if isinstance(data, dict) else None
        if not isinstance(raters, dict) or not all(
                isinstance(v, str) and re.fullmatch(r"[0-9a-f]{64}", v) for v in raters.values()):
            raise ValueError(f"{self.path}: field 'raters' must map rater names to SHA-256 hex digests")
        return dict(raters)

    def _write(self, hashes: dict[str, str]) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(self.path.name + ".tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as out:
            json.dump({"raters": dict(sorted(hashes.items()))}, out, indent=1)
            out.write("\n")
        os.replace(tmp, self.path)
        self._seen = None
