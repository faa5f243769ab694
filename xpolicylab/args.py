"""Hydra-style ``key=value`` arguments for the xpolicylab commands, without depending on Hydra.

``dojo policy ...`` passes the same strings through, so both front ends share the parsing, the defaults and the
error messages (an unknown key names the closest valid one; a bad value says what was expected).
"""

from __future__ import annotations

import difflib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any


class UsageError(ValueError):
    """Bad command-line arguments; the CLI prints the message and exits with status 2."""


@dataclass(frozen=True)
class Option:
    """One ``key=value`` option: its type (``str``, ``int``, ``float``, ``bool``, ``list``), default and help."""

    name: str
    type: str
    default: Any
    help: str


def parse_scalar(text: str) -> Any:
    """``true``/``false``/``null``, integers and floats become Python values; anything else stays a string."""
    lowered = text.strip().lower()
    if lowered in ("true", "false"):
        return lowered == "true"
    if lowered in ("null", "none", "~"):
        return None
    for convert in (int, float):
        try:
            return convert(text)
        except ValueError:
            pass
    if len(text) >= 2 and text[0] == text[-1] and text[0] in "'\"":
        return text[1:-1]
    return text


def _convert(option: Option, raw: str) -> Any:
    if option.type == "str":
        return None if raw.lower() in ("null", "none") else raw
    if option.type == "list":
        body = raw.strip()
        if body.startswith("[") and body.endswith("]"):
            body = body[1:-1]
        return tuple(item.strip() for item in body.split(",") if item.strip())
    if option.type == "bool":
        value = parse_scalar(raw)
        if not isinstance(value, bool):
            raise UsageError(f"{option.name}={raw}: expected true or false")
        return value
    try:
        return int(raw) if option.type == "int" else float(raw)
    except ValueError:
        raise UsageError(f"{option.name}={raw}: expected {'an integer' if option.type == 'int' else 'a number'}") \
            from None


def closest(name: str, candidates: Sequence[str]) -> str:
    """The most similar candidate, for 'did you mean' messages (a key the name abbreviates wins)."""
    prefixed = [c for c in candidates if c.startswith(name)] if name else []
    if prefixed:
        return min(prefixed, key=len)
    matches = difflib.get_close_matches(name, candidates, n=1, cutoff=0.0)
    return matches[0] if matches else ""


def parse(argv: Sequence[str], options: Sequence[Option], command: str,
          free_prefix: str | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """Parse ``key=value`` tokens. Returns (options with defaults filled in, free ``prefix.key`` values).

    ``free_prefix`` (e.g. ``policy``) lets ``policy.anything=value`` through for a user policy's own config.
    """
    by_name = {o.name: o for o in options}
    values = {o.name: o.default for o in options}
    free: dict[str, Any] = {}
    for token in argv:
        key, sep, raw = token.partition("=")
        key = key.strip().lstrip("+")
        if not sep or not key:
            raise UsageError(f"`{command}` takes key=value arguments, got {token!r} "
                             f"(e.g. {options[0].name}={options[0].default})")
        if free_prefix and key.startswith(free_prefix + "."):
            free[key[len(free_prefix) + 1:]] = parse_scalar(raw)
            continue
        if key not in by_name:
            hint = closest(key, list(by_name))
            raise UsageError(f"unknown key {key!r} for `{command}`; did you mean {hint!r}? "
                             f"Valid keys: {', '.join(by_name)}")
        values[key] = _convert(by_name[key], raw)
    return values, free


def help_text(command: str, summary: str, options: Sequence[Option], example: str) -> str:
    """The ``--help`` page of one command."""
    width = max(len(o.name) for o in options)
    lines = [f"usage: {command} [key=value ...]", "", summary, "", "keys:"]
    for o in options:
        default = "" if o.default is None else f" (default: {','.join(o.default) if o.type == 'list' else o.default})"
        lines.append(f"  {o.name:<{width}}  {o.help}{default}")
    lines += ["", "example:", f"  {example}"]
    return "\n".join(lines)
