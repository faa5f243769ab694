"""The CPU reference backend on MuJoCo itself, and MuJoCo's offscreen renderer."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from dojo.backends.registry import BackendOptions
    from dojo.backends.mujoco.backend import MujocoBackend


def make(options: BackendOptions) -> MujocoBackend:
    """The registry's constructor (`dojo.backends.registry`); setting `threads` (0 or absent: every core)."""
    from dojo.backends.mujoco.backend import MujocoBackend

    return MujocoBackend(num_threads=int(options.settings.get("threads") or 0) or None, cameras=options.cameras,
                         width=options.width, height=options.height, depth=options.depth,
                         privileged=options.privileged,
                         plan_paths=options.plan_paths if options.privileged else None)


def unsupported(features: Sequence[str], settings: Mapping[str, Any]) -> dict[str, str]:
    """Nothing: the CPU reference runs every feature MuJoCo has, scripted actors and events included."""
    return {}
