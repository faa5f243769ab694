"""The experiment parameters a policy package shares between its scripts (``deploy.yml``).

Deliberately a flat ``key: value`` file read without PyYAML: the shell scripts, ``deploy.py`` and ``model.py``
must all see the same dataset, task, checkpoint, robot, action type and seed, and a policy environment should
not need more than xpolicylab's own dependencies to read them.
"""

from __future__ import annotations

import shlex
from pathlib import Path
from typing import Any

from xpolicylab.args import UsageError, closest, parse_scalar


def load_params(path: str | Path) -> dict[str, Any]:
    """Read a flat ``key: value`` file (``#`` comments, scalars only)."""
    params: dict[str, Any] = {}
    for number, line in enumerate(Path(path).read_text(encoding="utf-8").splitlines(), start=1):
        text = line.split(" #", 1)[0].strip() if not line.lstrip().startswith("#") else ""
        if not text:
            continue
        key, sep, value = text.partition(":")
        if not sep or not key.strip().isidentifier():
            raise ValueError(f"{path}:{number}: expected 'key: value', got {line.strip()!r}")
        params[key.strip()] = parse_scalar(value.strip())
    return params


def apply_overrides(params: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Apply ``key=value`` overrides; only keys already in the file are accepted (typos are errors)."""
    out = dict(params)
    for token in overrides:
        key, sep, value = token.partition("=")
        if not sep or key not in params:
            hint = closest(key, list(params)) if sep else ""
            raise UsageError(f"bad override {token!r}" + (f"; did you mean {hint!r}?" if hint else
                                                          "; expected key=value"))
        out[key] = parse_scalar(value)
    return out


def resolve(params: dict[str, Any]) -> dict[str, Any]:
    """Fill ``{key}`` references in string values from the other parameters, so that e.g.
    ``checkpoint: checkpoints/{task}/seed{seed}`` follows a ``seed=1`` override."""
    out = dict(params)
    for key, value in params.items():
        if isinstance(value, str):
            for ref, sub in params.items():
                if ref != key:
                    value = value.replace("{" + ref + "}", "" if sub is None else str(sub))
            out[key] = value
    return out


def experiment_params(path: str | Path, overrides: list[str]) -> dict[str, Any]:
    """What a package's scripts see: the file, then the command line's overrides, then references resolved."""
    return resolve(apply_overrides(load_params(path), overrides))


def shell_exports(params: dict[str, Any]) -> str:
    """``export KEY=value`` lines (keys upper-cased) for ``eval "$(python deploy.py env)"``."""
    def text(value: Any) -> str:
        if isinstance(value, bool):
            return "true" if value else "false"
        return "" if value is None else str(value)

    return "\n".join(f"export {key.upper()}={shlex.quote(text(value))}" for key, value in params.items())
