"""plugged(plug, socket): a plug (a key's tip, a charger's prong tips: an `object/annotation` point at the end
that goes in first) is seated in a socket (an annotation box from the socket's entrance, its top, to its floor,
its bottom: a keyway, a pair of prong slots), within tolerances.

Seated means the plug's point is within `pos_tol` metres of the socket box's bottom centre (in 3D: a plug resting
on the socket's face, or pushed in beside the slot, is far above its floor) and the plug's heading (its frame's x
axis about the vertical) is within `yaw_tol` degrees of the socket's, compared as axes: a symmetric key or
charger turned half round fits the same socket. The tolerances are the task's numbers, written in the spec and
copied into the compiled program as they are; no setting (the Generalization random one included) changes them,
so they bind however the scene is drawn. The socket box may sit on a moving part (a lock's cylinder): seated
then follows the part as it turns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from dojo.backends import predicates as P
from dojo.backends.rotations import wrap_angle, yaw_of

from dojo.language.predicate_registry import OBJREF, PredicateWord, register

SCHEMA = {
    "description": "The plug's leading point is seated at the bottom of the socket's box, within pos_tol metres of "
                   "its bottom centre, its heading within yaw_tol degrees of the socket's (as an axis). Example: "
                   "{plugged: {plug: key/tip, socket: lock/keyhole, pos_tol: 0.002, yaw_tol: 8}}.",
    "type": "object",
    "additionalProperties": False,
    "required": ["plug", "socket", "pos_tol", "yaw_tol"],
    "properties": {
        "plug": {"description": "The plug's leading point: object/annotation (a key's `tip`).", "$ref": OBJREF},
        "socket": {"description": "The socket: object/annotation of a box from entrance (top) to floor (bottom).",
                   "$ref": OBJREF},
        "pos_tol": {"description": "Position tolerance in metres (the task's; no setting loosens it).",
                    "type": "number", "exclusiveMinimum": 0},
        "yaw_tol": {"description": "Heading tolerance in degrees (the task's; no setting loosens it).",
                    "type": "number", "exclusiveMinimum": 0, "maximum": 90},
    },
}


@dataclass(frozen=True)
class Plugged:
    plug: int
    socket: int
    pos_tol: float
    yaw_tol: float
    """Radians."""


def compile_plugged(ctx, arg, ref, bound) -> Plugged:
    return Plugged(ctx.frame(ref(arg["plug"])), ctx.frame(ref(arg["socket"])), float(arg["pos_tol"]),
                   math.radians(float(arg["yaw_tol"])))


def seated(xp, plug: tuple, socket: tuple, pos_tol: float, yaw_tol: float):
    """bool[N]: the plug frame's reference point at the socket box's bottom centre and headings matched (as axes);
    frames as in `dojo.backends.predicates` (pos, mat, c, h), yaw_tol in radians."""
    pp, mp, cp, _ = plug
    ps, ms, cs, hs = socket
    floor = P.box_center(xp, ps, ms, cs) - ms[:, :, 2] * hs[:, 2:3]
    close = xp.linalg.norm(P.box_center(xp, pp, mp, cp) - floor, axis=-1) <= pos_tol
    turn = wrap_angle(xp, yaw_of(xp, mp) - yaw_of(xp, ms))
    return close & (xp.abs(wrap_angle(xp, 2.0 * turn)) <= 2.0 * yaw_tol)


def evaluate_plugged(ev, node: Plugged):
    return seated(ev.xp, ev.frame(node.plug), ev.frame(node.socket), node.pos_tol, node.yaw_tol)


register(PredicateWord("plugged", SCHEMA, compile_plugged, Plugged, evaluate_plugged))
