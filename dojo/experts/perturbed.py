"""The tolerance check: the scripted expert aiming its fits a few millimetres off.

A Precision task's tolerances are meant to bind: a tube fits its hole, a coin the bank's slot, a screw's shaft the
nut's socket only when it is brought there within a millimetre or two. The check runs the expert with the target
of every fitting step (a skill word registered with `inserts`: insert, plug, screw) believed `distance` away from
where it is, in a horizontal direction drawn for each target, and everything else as it is. The expert still
measures and corrects the object it holds, towards the target it believes in, so it misses by that distance.
Tasks whose expert succeeds at 3 mm would accept a policy that is as far off: the validity table shows this
column (`perturbed`) for every task whose expert fits something, and it should be well below the expert's.

Each direction comes from the episode's own stream (`perturbation_rng`), so a run repeats exactly.
"""

from __future__ import annotations

import hashlib
import math
from typing import Any

import numpy as np

from dojo.language import skills as skill_words

from dojo.experts.oracle import OraclePolicy, ScriptedExpert
from dojo.experts.skills import expand

PERTURB_DISTANCE = 0.003
"""How far (m) the perturbed expert believes each fitting target to be from where it is (the issue's bar)."""


def perturbation_rng(plan: Any) -> np.random.Generator:
    """The perturbed expert's directions for one episode (PCG64 from a hash of the plan)."""
    digest = hashlib.sha256(f"robodojo-perturbed|{plan.hash}".encode()).digest()
    return np.random.Generator(np.random.PCG64(int.from_bytes(digest[:16], "little")))


def fits(steps: list[dict[str, Any]]) -> list[str]:
    """The targets (`object/annotation`) of the fitting steps among `steps`, in order, each once."""
    targets: list[str] = []
    for step in steps:
        word = skill_words.word(step.get("skill", ""))
        target = step.get("target")
        if word is not None and word.inserts and isinstance(target, str) and "/" in target and target not in targets:
            targets.append(target)
    return targets


def aim_offsets(plan: Any, steps: list[dict[str, Any]], distance: float) -> dict[str, np.ndarray]:
    """World offsets, `distance` long and horizontal, of each fitting target of the expert's steps."""
    rng = perturbation_rng(plan)
    out = {}
    for target in fits(expand(plan, steps)):
        angle = float(rng.uniform(0.0, 2.0 * math.pi))
        out[target] = distance * np.array([math.cos(angle), math.sin(angle), 0.0])
    return out


def has_fits(task: Any) -> bool:
    """Whether a task's expert fits something (the tasks the perturbed column is run on)."""
    return bool(fits(list(task.data.get("expert", []))))


class PerturbedOracle(OraclePolicy):
    """PRIVILEGED like the oracle, but each episode's expert aims its fitting targets `distance` metres off (config
    `distance`, default PERTURB_DISTANCE)."""

    def __init__(self, config: dict[str, Any] | None = None) -> None:
        super().__init__(config)
        self.distance = float(self.config.get("distance", PERTURB_DISTANCE))

    def new_expert(self, plan: Any) -> ScriptedExpert:
        steps = self.expert_steps(plan.task)
        return ScriptedExpert(plan, steps, shifts=aim_offsets(plan, steps, self.distance))
