"""What the mjx backend cannot run, from the features a plan requires (`plan.requires`, `dojo.compiler.plan_features`).

The answer comes from MJX itself where it keeps one: the geometry pairs MJX's JAX implementation collides are the
keys of its collision table, so a MuJoCo release that adds a pair is picked up without a change here. MJX has no
flex (cloth), and this backend does not run a task's scripted actors or events.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import mujoco

NOT_RUN = {
    "flex": "MJX does not simulate flex (deformable bodies such as cloth)",
    "equality:flex": "MJX does not simulate flex (deformable bodies such as cloth)",
    "actors": "the mjx backend does not run a task's scripted actors",
    "events": "the mjx backend does not run a task's scripted events",
}


def unsupported(features: Iterable[str], settings: Mapping[str, Any]) -> dict[str, str]:
    """Each feature in `features` this backend cannot run, with the reason (empty: it runs them all)."""
    pairs = _collision_pairs()
    out = {}
    for feature in features:
        if feature in NOT_RUN:
            out[feature] = NOT_RUN[feature]
        elif feature.startswith("contact:"):
            a, _, b = feature.removeprefix("contact:").partition("-")
            if frozenset((a, b)) not in pairs:
                out[feature] = f"MJX does not collide {a} with {b} geometry"
    return out


def _collision_pairs() -> set[frozenset[str]]:
    """The geom type pairs MJX collides, as lower-case MuJoCo type names (`{"box", "mesh"}`)."""
    from mujoco.mjx._src.collision_driver import _COLLISION_FUNC  # MJX's own table: no private copy to go stale

    def name(t: Any) -> str:
        return mujoco.mjtGeom(int(t)).name.removeprefix("mjGEOM_").lower()

    return {frozenset((name(a), name(b))) for a, b in _COLLISION_FUNC}
