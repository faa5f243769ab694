"""Backends by name: `make_backend("mujoco", options)` builds any backend, so no caller constructs one by hand.

A backend is one subpackage of `dojo.backends` whose `__init__` defines `make(options: BackendOptions) -> Backend`
and `unsupported(features, settings) -> {feature: reason}` (which of a plan's `requires` it cannot run), may define
`check(settings)` (refuse settings it cannot take, before a run starts), plus one
Hydra config file (`dojo/cli/config/backend/<name>.yaml`) whose keys other than `name` reach `make` as
`options.settings`; one that implements `Backend.attach_rule` also sets `RUNS_POLICY_RULES = True`. The runtime
names a backend by its config; this module imports the package only when asked, so choosing `mujoco` never
imports JAX.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from dojo.backends.base import Backend


@dataclass(frozen=True)
class BackendOptions:
    """What every backend is built from. `settings` holds the backend's own config keys (threads, impl, ...)."""

    cameras: tuple[str, ...] = ()
    width: int = 640
    height: int = 480
    depth: bool = False
    privileged: bool = False
    """Observations carry the simulator state (for privileged reference policies, the oracle, only)."""
    plan_paths: Mapping[str, str] | None = None
    """Plan hash -> plan file, for privileged observations and for backends that preload every plan."""
    action_modes: tuple[str, ...] | None = None
    """The action modes the policy will send (None: any); a compiling backend (mjx) builds only what they need."""
    settings: Mapping[str, Any] = field(default_factory=dict)


def available() -> list[str]:
    """The backend subpackages installed (their names, without importing them)."""
    import dojo.backends as package

    return sorted(m.name for m in pkgutil.iter_modules(package.__path__) if m.ispkg)


def make_backend(name: str, options: BackendOptions) -> Backend:
    """A new backend `name` built from `options`."""
    if name not in available():
        raise ValueError(f"unknown backend {name!r}; one of {', '.join(available())}")
    make = getattr(importlib.import_module(f"dojo.backends.{name}"), "make", None)
    if make is None:
        raise ValueError(f"dojo.backends.{name} defines no make(options): it is not a backend")
    return make(options)


def unsupported_features(name: str, features: Sequence[str], settings: Mapping[str, Any]) -> dict[str, str]:
    """Each of `features` (a plan's `requires`) that backend `name`, configured with `settings`, cannot run,
    with its reason. Every backend package answers through its `unsupported(features, settings)`, without being
    built, so a run can send a plan elsewhere before it starts."""
    if name not in available():
        raise ValueError(f"unknown backend {name!r}; one of {', '.join(available())}")
    answer = getattr(importlib.import_module(f"dojo.backends.{name}"), "unsupported", None)
    if answer is None:
        raise ValueError(f"dojo.backends.{name} defines no unsupported(features, settings): it is not a backend")
    return dict(answer(list(features), settings))


def runs_policy_rules(name: str) -> bool:
    """Whether backend `name` can run a policy's rule inside its own step (`Backend.attach_rule`), answered
    without building it, so that a run knows before it starts where its policy will run: the package says so with
    `RUNS_POLICY_RULES = True`. Unknown names (a test's stand-in backend) cannot."""
    if name not in available():
        return False
    return bool(getattr(importlib.import_module(f"dojo.backends.{name}"), "RUNS_POLICY_RULES", False))


def check_settings(name: str, settings: Mapping[str, Any]) -> None:
    """Refuse settings backend `name` cannot take, by name, without building it: a package may define
    `check(settings)`, which raises `ValueError`. The loop builds its backend only when it has work, after the run
    has started; a typo in a setting fails here, before anything runs."""
    if name not in available():
        raise ValueError(f"unknown backend {name!r}; one of {', '.join(available())}")
    check = getattr(importlib.import_module(f"dojo.backends.{name}"), "check", None)
    if check is not None:
        check(settings)


def backend_factory(name: str, options: BackendOptions) -> Callable[[], Backend]:
    """A factory for the evaluation loop, which builds its backend when it has work (and closes it after); the
    settings are checked now (`check_settings`)."""
    if name in available():  # a test's stand-in backend has no package to ask
        check_settings(name, options.settings)
    return lambda: make_backend(name, options)


def factory_from_config(config: Mapping[str, Any], **options: Any) -> Callable[[], Backend]:
    """A factory for the backend a config names: `config` is the backend config group's content (its `name`
    and the backend's own settings, as plain data); `options` are the other `BackendOptions` fields."""
    settings = {k: v for k, v in config.items() if k != "name"}
    return backend_factory(str(config["name"]), BackendOptions(settings=settings, **options))
