"""The success and score predicates of DESIGN section 4, written once over an array namespace.

Each function takes `xp` (numpy or jax.numpy) and batched arrays with a leading environment axis N, and returns
bool[N]. They are pure and branch-free, so the CPU backend calls them with NumPy and the MJX backend calls the
very same code under `jax.jit`/`vmap`. `predicate_program` compiles a plan's program into calls of these.

Everything a predicate looks at is a *frame*: a world position `pos [N, 3]`, a rotation `mat [N, 3, 3]`
(world = mat @ local, MuJoCo's xmat) and a box in that frame, centre `c [N, 3]` and half extents `h [N, 3]`:
- an object: its root body's frame and the bounding box of its collision geoms (computed from the model, so the
  box is right whatever the asset's origin convention);
- an annotation `obj/name`: the site's frame; its box is the site's size (a placement box) or a point;
- a region: a flat rectangle on its support surface, identity rotation;
- `table`: the table body, like an object.
The *reference point* of a frame is its box centre (`box_center`).

Tolerances that the task language leaves implicit are module constants here, one place for all backends.
"""

from __future__ import annotations

import math
from typing import Any

from dojo.backends.rotations import wrap_angle, yaw_of

Array = Any

SUPPORT_TOLERANCE = 0.02
"""on(): a's lowest point may be this far above or below the support's top surface (m)."""
FOOTPRINT_MARGIN = 0.005
"""on()/inside(): the reference point may overhang the support's or container's box by this much (m)."""
UPRIGHT_DEGREES = 15.0
"""upright(): the object's up axis within this angle of world z (task schema)."""
REGION_HEIGHT = 0.3
"""inside(a, region): a region is a box this tall above its surface."""
TOUCH_DISTANCE = 0.0
"""A contact counts as touching when its signed distance is at most this: geoms in contact or penetrating.
The same test on MuJoCo's contact list (which may include contacts within a geom margin) and on MJX's
fixed-size contact arrays (whose unused rows carry positive distances) gives the same answer."""
PRESS_DOWN = 0.7
PRESS_UP = 0.3
"""pressed(): a button is down once its joint travelled PRESS_DOWN of the way from rest to the far end of its
range, and up again below PRESS_UP (hysteresis, so a jittering cap is counted once). For the push button
asset (rest 0, range [-0.01, 0]) down means q < -0.007, its documented threshold."""


def box_center(xp: Any, pos: Array, mat: Array, c: Array) -> Array:
    """World position [N, 3] of a frame's box centre."""
    return pos + xp.einsum("nij,nj->ni", mat, c)


def world_half_extents(xp: Any, mat: Array, h: Array) -> Array:
    """Half extents [N, 3] of the world-axis-aligned box around a rotated box (|R| @ h)."""
    return xp.einsum("nij,nj->ni", xp.abs(mat), h)


def local_offset(xp: Any, point: Array, pos: Array, mat: Array, c: Array) -> Array:
    """`point` [N, 3] in a frame's box coordinates (relative to the box centre, frame axes)."""
    return xp.einsum("nji,nj->ni", mat, point - box_center(xp, pos, mat, c))


def supported(xp: Any, a: tuple, support: tuple) -> Array:
    """a's box centre lies over the support box and a's lowest point is at the support's top surface.

    `a` and `support` are frames (pos, mat, c, h). The top surface is the highest point of the support box in
    world z, so a tilted support still has a sensible top; the footprint test is in the support's own axes.
    """
    pa, ma, ca, ha = a
    ps, ms, cs, hs = support
    centre_a = box_center(xp, pa, ma, ca)
    off = local_offset(xp, centre_a, ps, ms, cs)
    over = xp.all(xp.abs(off[:, :2]) <= hs[:, :2] + FOOTPRINT_MARGIN, axis=-1)
    top = box_center(xp, ps, ms, cs)[:, 2] + world_half_extents(xp, ms, hs)[:, 2]
    bottom = centre_a[:, 2] - world_half_extents(xp, ma, ha)[:, 2]
    return over & (xp.abs(bottom - top) <= SUPPORT_TOLERANCE) & (centre_a[:, 2] > top)


def on(xp: Any, a: tuple, support: tuple, touching: Array) -> Array:
    """on(a, b): a rests on b: `supported` and, for objects, in contact (`touching`; all-True for regions)."""
    return supported(xp, a, support) & touching


def inside(xp: Any, a: tuple, container: tuple, up: float = 0.0) -> Array:
    """inside(a, container): a's box centre is within the container box (its `inside` placement box, else its
    bounding box), the box extended upwards by `up` metres (used for regions, which are flat)."""
    pa, ma, ca, _ = a
    pc, mc, cc, hc = container
    off = local_offset(xp, box_center(xp, pa, ma, ca), pc, mc, cc)
    lo = -hc - FOOTPRINT_MARGIN
    hi = hc + FOOTPRINT_MARGIN + up * xp.asarray([0.0, 0.0, 1.0])
    return xp.all((off >= lo) & (off <= hi), axis=-1)


def upright(xp: Any, mat: Array) -> Array:
    """upright(a): the frame's z axis is within UPRIGHT_DEGREES of world z."""
    return mat[:, 2, 2] >= math.cos(math.radians(UPRIGHT_DEGREES))


def lifted(xp: Any, pos: Array, mat: Array, c: Array, initial_center: Array, height: float) -> Array:
    """lifted(a, h): a's box centre is at least h above where it was at the start of the episode."""
    return box_center(xp, pos, mat, c)[:, 2] - initial_center[:, 2] >= height


def joint_at_least(xp: Any, q: Array, value: float) -> Array:
    """joint_at_least(obj/joint, v): the joint position q [N] is at least v."""
    return q >= value


def joint_at_most(xp: Any, q: Array, value: float) -> Array:
    """joint_at_most(obj/joint, v): the joint position q [N] is at most v."""
    return q <= value


def aligned(xp: Any, a: tuple, target: tuple, pos_tol: float, yaw_tol_deg: float) -> Array:
    """aligned(object, target): a planar pose match, as its yaw tolerance implies: reference points within
    pos_tol in the ground plane and headings about world z within yaw_tol degrees. (Heights are left out: a
    T-shape lying on a target outline has its centre above the outline's.)"""
    pa, ma, ca, _ = a
    pt, mt, ct, _ = target
    delta = box_center(xp, pa, ma, ca)[:, :2] - box_center(xp, pt, mt, ct)[:, :2]
    close = xp.linalg.norm(delta, axis=-1) <= pos_tol
    dyaw = xp.abs(wrap_angle(xp, yaw_of(xp, ma) - yaw_of(xp, mt)))
    return close & (dyaw <= math.radians(yaw_tol_deg))


def near(xp: Any, a: tuple, b: tuple, distance: float, planar: bool) -> Array:
    """near(a, b, d): reference points within d metres (in the ground plane when `planar`)."""
    delta = box_center(xp, a[0], a[1], a[2]) - box_center(xp, b[0], b[1], b[2])
    if planar:
        delta = delta[:, :2]
    return xp.linalg.norm(delta, axis=-1) <= distance


def touched(xp: Any, contact: Array, atoms_a: tuple[int, ...], atoms_b: tuple[int, ...]) -> Array:
    """touched(a, b): some contact between a geom of a and a geom of b. `contact` is the symmetric bool
    [N, A, A] matrix of `contact_matrix`; a and b are sets of atoms (`robot` is both arms)."""
    hit = xp.zeros(contact.shape[:1], dtype=bool)
    for i in atoms_a:
        for j in atoms_b:
            hit = hit | contact[:, i, j]
    return hit


def contact_matrix(xp: Any, geom_atom: Array, geom1: Array, geom2: Array, dist: Array, n_atoms: int) -> Array:
    """Symmetric bool [N, A, A]: which atoms (objects, the table, each arm) touch which.

    `geom_atom` [ngeom] int maps a geom to its atom or to `n_atoms` (not tracked); `geom1`, `geom2`, `dist`
    [N, C] are the contacts (MuJoCo's `data.contact` rows, or MJX's fixed-size `data.contact`, whose inactive
    rows have a large `dist`). One-hot products instead of scatter, so it is the same code in NumPy and JAX.
    """
    atoms = xp.arange(n_atoms + 1)
    active = (dist <= TOUCH_DISTANCE)[..., None]
    one1 = (geom_atom[geom1][..., None] == atoms) & active
    one2 = geom_atom[geom2][..., None] == atoms
    hits = xp.einsum("nca,ncb->nab", one1.astype(xp.float32), one2.astype(xp.float32)) > 0
    hits = hits | xp.swapaxes(hits, -1, -2)
    return hits[:, :n_atoms, :n_atoms]


def pool_contact_matrix(xp: Any, geom_atom: Array, geom: Array, dist: Array, worldid: Array, count: Array,
                        n_worlds: int, n_atoms: int) -> Array:
    """`contact_matrix` of a batch whose contacts share one pool, as MuJoCo Warp keeps them (MJX `impl='warp'`).

    `geom [P, 2]`, `dist [P]` and `worldid [P]` are the pool's rows, of which the first `count` (a scalar or [1]
    array, Warp's `nacon`) are this step's; later rows are stale and ignored, as are rows of a world outside the
    batch. Each touching row adds one to its world's (atom, atom) cell with a scatter-add: a one-hot product over
    worlds, as `contact_matrix` does over rows, would cost pool rows x worlds. Same bool [N, A, A] result.
    """
    a = n_atoms + 1
    filled = xp.arange(dist.shape[0]) < xp.reshape(xp.asarray(count), (-1,))[0]
    active = filled & (dist <= TOUCH_DISTANCE) & (worldid >= 0) & (worldid < n_worlds)
    last = geom_atom.shape[0] - 1
    atom1 = geom_atom[xp.clip(geom[:, 0], 0, last)]
    atom2 = geom_atom[xp.clip(geom[:, 1], 0, last)]
    cell = (xp.clip(worldid, 0, n_worlds - 1) * a + atom1) * a + atom2
    counts = _scatter_add(xp, n_worlds * a * a, cell, active.astype(xp.float32))
    hits = xp.reshape(counts, (n_worlds, a, a)) > 0
    hits = hits | xp.swapaxes(hits, -1, -2)
    return hits[:, :n_atoms, :n_atoms]


def _scatter_add(xp: Any, size: int, index: Array, values: Array) -> Array:
    """A zero vector of `size` with `values` added at `index` (repeats accumulate), in NumPy or JAX."""
    out = xp.zeros(size, dtype=values.dtype)
    if hasattr(out, "at"):  # a JAX array: functional update
        return out.at[index].add(values)
    xp.add.at(out, index, values)
    return out


def press_down(xp: Any, q: Array, rest: Array, far: Array, was_down: Array) -> Array:
    """Whether each button is down now, from its joint position q, rest position and far range end (all [N, P]),
    with hysteresis on `was_down`."""
    depth = (rest - q) / (rest - far)
    return xp.where(was_down, depth > PRESS_UP, depth > PRESS_DOWN)


def count_presses(xp: Any, count: Array, was_down: Array, down: Array) -> Array:
    """pressed(): press counts [N, P] advanced by each up -> down transition."""
    return count + (down & ~was_down).astype(count.dtype)
