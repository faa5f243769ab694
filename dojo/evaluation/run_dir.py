"""Where `dojo` writes: one results root, and one folder per run named by a short, filesystem-safe key.

A run's folder is `<root>/<suite>/<policy>/<key>` whether it was started alone or by a `-m` sweep, so re-running
a command resumes it and `dojo report <root>/<suite>/<policy>` finds it right after a sweep. The key names the
overrides that change what is evaluated (`episodes=1_seeds=0-1`), sorted, with every character a shell or a file
system treats specially replaced (`[0,1]` -> `0-1`, `a/b:c` -> `a-b-c`); long values keep a readable head and a
hash. Overrides that change only how a run is executed (batch size, progress display, where results and reports
go, the policy server's address) are left out of the key, so changing them resumes the same run. With no such
override the key is `default`, so every run of a policy sits at the same depth.

The root is `outputs` in the current folder, or `$DOJO_OUTPUTS`; reports, `dojo show` images and leaderboards go
under it too, never loose in the folder the user happens to be in.
"""

from __future__ import annotations

import hashlib
import os
import re
from collections.abc import Iterable
from pathlib import Path
from typing import Any

ROOT_ENV = "DOJO_OUTPUTS"
DEFAULT_ROOT = "outputs"
DEFAULT_KEY = "default"
RESOLVER = "dojo_run_key"
LINK_SETTINGS = ("columnar", "on_device", "shared_memory", "token")
"""Policy config keys that say how to reach or run the policy, not which policy it is, so neither a run's folder
nor its id (`policy_link.policy_identity`) holds them: `on_device` (where the policy runs changes no result of a
rule that `matches_host`; a run whose results it does change says so in its identity itself), `shared_memory` and
`columnar` (the same images by another way, or laid out otherwise) and `token` (a secret, which must never be
written into a path or, in plain text, into the results store; a new token reaches the same server)."""
# Config groups already named by the folders above the key, settings that do not change the results, and where and
# how a policy is served or run (a server's address is not what is evaluated, and the `LINK_SETTINGS`; the run id
# inside the store still tells runs of different servers apart).
NOT_IN_KEY = frozenset({"suite", "policy", "results", "report", "num_envs", "progress", "jobs", "plans",
                        "episode_timeout_s", "policy.url", *(f"policy.{key}" for key in LINK_SETTINGS)})
# Groups none of whose keys change the results: where a run executes (`launcher=ray launcher.workers=4` resumes
# the run that `launcher=local` started) and Hydra's own.
NOT_IN_KEY_GROUPS = frozenset({"hydra", "launcher"})
MAX_VALUE = 32  # characters of a value kept whole; longer ones are cut and given a hash
MAX_KEY = 96
_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")


def results_root() -> Path:
    """The folder every `dojo` output goes under by default."""
    return Path(os.environ.get(ROOT_ENV) or DEFAULT_ROOT)


def _short(text: str, limit: int) -> str:
    if len(text) <= limit:
        return text
    digest = hashlib.sha256(text.encode()).hexdigest()[:8]
    return f"{text[:limit - 9].rstrip('-.')}-{digest}"


def _safe(value: Any) -> str:
    """A value as folder-name text: list items joined by `-`, unsafe characters replaced by `-`."""
    if isinstance(value, (list, tuple)):
        text = "-".join(_safe(v) for v in value)
    elif isinstance(value, dict):
        text = "-".join(f"{_safe(k)}.{_safe(v)}" for k, v in value.items())
    else:
        text = _UNSAFE.sub("-", str(value)).strip("-")
    return _short(text, MAX_VALUE) or "none"


def run_key(overrides: Iterable[str]) -> str:
    """The folder name of a run given its command-line overrides (one job's, without sweeps)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parts: dict[str, str] = {}  # a key given twice counts once, with its last value (as Hydra composes it)
    for override in OverridesParser.create().parse_overrides([str(o) for o in overrides]):
        key = override.key_or_group
        if key in NOT_IN_KEY or key.split(".", 1)[0] in NOT_IN_KEY_GROUPS:
            continue
        if override.is_delete():
            parts[key] = f"no-{_safe(key)}"
        elif override.is_sweep_override():
            parts[key] = f"{_safe(key)}={_safe(override.input_line.split('=', 1)[1])}"
        else:
            parts[key] = f"{_safe(key)}={_safe(override.value())}"
    return _short("_".join(sorted(parts.values())), MAX_KEY) or DEFAULT_KEY


def register_resolver() -> None:
    """`${dojo_run_key:${hydra.overrides.task}}` in the Hydra config of `dojo run`."""
    from omegaconf import OmegaConf

    if not OmegaConf.has_resolver(RESOLVER):
        OmegaConf.register_new_resolver(RESOLVER, lambda overrides: run_key(list(overrides or [])))
