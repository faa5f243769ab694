"""tightened(screw, object/hinge, turns): the screw is seated in a thread and the thread has been turned at least
`turns` full turns from its rest.

A thread is an asset's `threads:` entry (asset.schema.json): a hinge whose turning drives a slide by the pitch,
coupled by a joint equality constraint. The hinge's link carries the socket the screw's shaft keys into (a
placement box annotation on that link): turning the screw turns the socket, and the socket sinks with the slide.
So "tightened" reads two things the simulator holds in both backends: the hinge's position (turns past its rest,
in the sense away from the rest end of its range, as `struck` takes its direction) and the screw's lowest point in
the lower half of that socket (a tip resting on its rim is not in), wherever the socket has sunk to. Either alone is
not enough: a socket turned by a shaft that was pulled out again, or a screw dropped into a nut and never turned,
is not a fastened screw."""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco

from dojo.backends import predicates as P
from dojo.backends.program_types import ProgramError

from dojo.language.predicate_registry import OBJREF, PredicateWord, register

SCHEMA = {
    "description": "[screw, object/hinge, turns]: the screw's lowest point is in the lower half of the socket on the "
                   "thread's hinge link and that hinge (a thread of the object's asset) has turned at least `turns` "
                   "full turns from its rest. Example: {tightened: [screw_a, nut_a/thread, 1.0]}.",
    "type": "array",
    "prefixItems": [{"$ref": OBJREF}, {"$ref": OBJREF}, {"type": "number", "exclusiveMinimum": 0}],
    "items": False,
    "minItems": 3,
}


@dataclass(frozen=True)
class Tightened:
    screw: int
    """Frame of the screw."""
    socket: int
    """Frame of the placement box on the hinge's link."""
    joint: int
    """The hinge's column in `state["qpos"]`."""
    rest: float
    direction: float
    """+1 or -1: the sign of a turn from the rest towards the far end of the hinge's range (tightening)."""
    angle: float
    """`turns` in radians."""


def thread_hinge(model: mujoco.MjModel, joint: str) -> bool:
    """Whether `joint` is the hinge of a thread: a hinge a joint equality couples a slide to."""
    jid = model.joint(joint).id
    if model.jnt_type[jid] != mujoco.mjtJoint.mjJNT_HINGE:
        return False
    return any(model.eq_type[e] == mujoco.mjtEq.mjEQ_JOINT and model.eq_obj2id[e] == jid
               and model.jnt_type[model.eq_obj1id[e]] == mujoco.mjtJoint.mjJNT_SLIDE for e in range(model.neq))


def socket_annotation(ctx, obj: str, joint: str) -> str:
    """The name of the placement box annotation on the link `joint` turns (the thread's socket)."""
    model = ctx.model
    body = int(model.jnt_bodyid[model.joint(joint).id])
    for annotation, site in sorted(ctx.plan.objects[obj]["sites"].items()):
        sid = model.site(site).id
        if int(model.site_bodyid[sid]) == body and model.site_type[sid] == mujoco.mjtGeom.mjGEOM_BOX:
            return annotation
    raise ProgramError(f"tightened: {joint!r} turns no socket (no placement box annotation on its link)")


def compile_tightened(ctx, arg, ref, bound) -> Tightened:
    name = ref(arg[1])
    column = ctx.joint(name)  # checks the name, listing the object's joints when it is wrong
    if not thread_hinge(ctx.model, name):
        raise ProgramError(f"tightened: {name!r} is not the hinge of a thread (an asset's `threads:` entry couples "
                           "a hinge to a slide)")
    obj = name.split("/", 1)[0]
    socket = ctx.frame(f"{obj}/{socket_annotation(ctx, obj, name)}")
    joint = ctx.model.joint(name)
    lo, hi = (float(v) for v in ctx.model.jnt_range[joint.id])
    rest = min(max(float(ctx.data.qpos[joint.qposadr[0]]), lo), hi)
    direction = -1.0 if abs(lo - rest) >= abs(hi - rest) else 1.0
    return Tightened(ctx.frame(ref(arg[0])), socket, column, rest, direction, 2.0 * math.pi * float(arg[2]))


def evaluate_tightened(ev, node: Tightened):
    xp = ev.xp
    pos, mat, c, h = ev.frame(node.screw)
    tip = P.box_center(xp, pos, mat, c) - P.world_half_extents(xp, mat, h) * xp.asarray([0.0, 0.0, 1.0])
    sp, sm, sc, sh = ev.frame(node.socket)
    off = P.local_offset(xp, tip, sp, sm, sc)
    # in the socket's lower half: a tip resting on the socket's rim, however near its axis, is not in
    seated = xp.all(xp.abs(off) <= sh + P.FOOTPRINT_MARGIN, axis=-1) & (off[:, 2] <= 0.0)
    turned = (ev.state["qpos"][:, node.joint] - node.rest) * node.direction >= node.angle - 1e-9
    return seated & turned


register(PredicateWord("tightened", SCHEMA, compile_tightened, Tightened, evaluate_tightened))
