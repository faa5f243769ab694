"""The simulator features a compiled plan uses (`plan.requires`), read off its model and its task spec.

A backend cannot run every scene: MJX collides only some pairs of geometry types and has no flex, a real robot
cannot run the scripted actors of a simulated world. The compiler says what each plan needs, as plain names, and
each backend says which of those it cannot do (`dojo.backends.registry.unsupported_features`); `dojo run` sends a
plan to a backend that can run it and says so. The compiler never names a backend: it states facts about the scene.

Feature names:
- `contact:<type>-<type>`: two kinds of geometry that may touch (MuJoCo geom type names, sorted, e.g.
  `contact:box-mesh`), for every pair of colliding geoms not both fixed to the world;
- `equality:<type>`: an equality constraint of that type (`connect`, `weld`, `joint`, `tendon`, `flex`);
- `flex`: deformable bodies (MuJoCo flex: cloth);
- `tendon`: tendons;
- `<key>` for each top-level key of the task spec that needs the simulator to act during an episode
  (`SCRIPTED_KEYS`: actors that move things by themselves, events that change the scene).
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

SCRIPTED_KEYS = ("actors", "events")
"""Task spec keys whose content the backend must run every step, by the key's name."""


def plan_features(model: mujoco.MjModel, task: dict[str, Any]) -> list[str]:
    """Every feature (module docstring) that a plan of `task` compiled to `model` uses, sorted."""
    features = set(_contact_pairs(model))
    for eq_type in np.unique(model.eq_type[: model.neq]):
        features.add(f"equality:{_type_name(mujoco.mjtEq(int(eq_type)), 'mjEQ_')}")
    if model.nflex:
        features.add("flex")
    if model.ntendon:
        features.add("tendon")
    features.update(key for key in SCRIPTED_KEYS if task.get(key))
    return sorted(features)


def _contact_pairs(model: mujoco.MjModel) -> set[str]:
    """`contact:a-b` for the geom type pairs MuJoCo's collision filter lets touch. Geoms are grouped by what the
    filter reads (type, contype, conaffinity, fixed to the world), so a scene of hundreds of geoms costs a few
    dozen group pairs; two groups of world-fixed geoms never collide, and neither do geoms of one body (MuJoCo
    skips those pairs too, which a group of one type on one body may over-report: a harmless `contact:` name)."""
    fixed = model.body_weldid[model.geom_bodyid] == 0
    groups = {(int(t), int(ct), int(ca), bool(f))
              for t, ct, ca, f in zip(model.geom_type, model.geom_contype, model.geom_conaffinity, fixed)}
    pairs: set[str] = set()
    ordered = sorted(groups)
    for i, (t1, ct1, ca1, f1) in enumerate(ordered):
        for t2, ct2, ca2, f2 in ordered[i:]:
            if (f1 and f2) or not ((ct1 & ca2) or (ct2 & ca1)):
                continue
            names = sorted(_type_name(mujoco.mjtGeom(t), "mjGEOM_") for t in (t1, t2))
            pairs.add(f"contact:{names[0]}-{names[1]}")
    for g1, g2 in zip(model.pair_geom1[: model.npair], model.pair_geom2[: model.npair]):
        names = sorted(_type_name(mujoco.mjtGeom(int(model.geom_type[g])), "mjGEOM_") for g in (g1, g2))
        pairs.add(f"contact:{names[0]}-{names[1]}")
    return pairs


def _type_name(value: Any, prefix: str) -> str:
    """`mjGEOM_BOX` -> `box`: MuJoCo's enum names as the lower-case words its XML uses."""
    return value.name.removeprefix(prefix).lower()
