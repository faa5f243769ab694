"""The simulation state the predicates read, gathered from MuJoCo (NumPy) or MJX (JAX) arrays.

A compiled program (see `predicate_program`) names a few *frames* (bodies, sites, constant frames such as
regions), a few joints and a few contact *atoms* (objects, the table, each arm). `StateIndex` holds where they
are in one model; `gather_state` turns a batch of simulation arrays into the predicate state

    {"pos": [N, F, 3], "mat": [N, F, 3, 3], "qpos": [N, J], "qvel": [N, V], "contact": bool [N, A, A]}

with the same code for both backends. The MJX backend calls `batched_state(jnp, index, const_pos, data)` on an
`mjx.Data` stacked over environments (all environments of a bucket share one model structure, hence one
`StateIndex`, which is hashable so it can be closed over under jit); the CPU backend calls `mujoco_state` for
one `MjData`. Both end in `gather_state`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import mujoco
import numpy as np

from dojo.backends.predicates import contact_matrix

Array = Any

BODY, SITE, CONST = 0, 1, 2
"""Frame kinds: a body (xpos/xmat), a site (site_xpos/site_xmat), or a constant world frame (a region)."""


@dataclass(frozen=True)
class StateIndex:
    """Where a program's frames, joints and atoms are in one compiled model. Hashable (tuples only)."""

    frame_kind: tuple[int, ...]
    frame_id: tuple[int, ...]
    """Body id for BODY frames, site id for SITE frames, -1 for CONST frames (pose from params)."""
    qpos_adr: tuple[int, ...]
    geom_atom: tuple[int, ...]
    """Per geom of the model: its atom, or n_atoms for geoms no predicate looks at."""
    n_atoms: int
    dof_adr: tuple[int, ...] = ()
    """Velocity addresses of the joints whose speed a predicate reads (`struck`), in `state["qvel"]` order."""

    @cached_property
    def arrays(self) -> dict[str, np.ndarray]:
        """The tuples as index arrays (built once; ids of the other kinds' frames replaced by 0)."""
        kind = np.asarray(self.frame_kind, dtype=np.int32).reshape(-1)
        ident = np.asarray(self.frame_id, dtype=np.int32).reshape(-1)
        return {"body": np.where(kind == BODY, ident, 0), "site": np.where(kind == SITE, ident, 0),
                "is_body": kind == BODY, "is_site": kind == SITE,
                "qpos": np.asarray(self.qpos_adr, dtype=np.int32).reshape(-1),
                "dof": np.asarray(self.dof_adr, dtype=np.int32).reshape(-1),
                "geom_atom": np.asarray(self.geom_atom, dtype=np.int32).reshape(-1)}


def gather_state(xp: Any, index: StateIndex, const_pos: Array, xpos: Array, xmat: Array, site_xpos: Array,
                 site_xmat: Array, qpos: Array, geom1: Array, geom2: Array, dist: Array,
                 qvel: Array | None = None) -> dict[str, Array]:
    """The predicate state of N environments.

    Arrays are batched over N: `xpos [N, nbody, 3]`, `xmat [N, nbody, 3, 3]` or `[N, nbody, 9]`, likewise
    the sites, `qpos [N, nq]`, contacts `geom1`, `geom2`, `dist [N, C]`; `const_pos [N, F, 3]` comes from the
    program's params (`params["const_pos"]`). A fixed number of gathers whatever the number of frames.
    `qvel [N, nv]` gives the speeds of the program's V joints (`index.dof_adr`, those `struck` reads), gathered
    like their positions, so environments whose models differ in size (clutter) batch together; without it they
    read as zero.
    """
    ix = index.arrays
    n = qpos.shape[0]
    xmat = xp.reshape(xmat, (n, -1, 3, 3))
    pos = xp.where(ix["is_body"][:, None], xpos[:, ix["body"]], const_pos)
    mat = xp.where(ix["is_body"][:, None, None], xmat[:, ix["body"]], xp.eye(3, dtype=xpos.dtype))
    if ix["is_site"].any():
        site_xmat = xp.reshape(site_xmat, (n, -1, 3, 3))
        pos = xp.where(ix["is_site"][:, None], site_xpos[:, ix["site"]], pos)
        mat = xp.where(ix["is_site"][:, None, None], site_xmat[:, ix["site"]], mat)
    return {
        "pos": pos,
        "mat": mat,
        "qpos": qpos[:, ix["qpos"]],
        "qvel": qvel[:, ix["dof"]] if qvel is not None else xp.zeros((n, len(index.dof_adr)), dtype=qpos.dtype),
        "contact": contact_matrix(xp, xp.asarray(ix["geom_atom"]), geom1, geom2, dist, index.n_atoms),
    }


def batched_state(xp: Any, index: StateIndex, const_pos: Array, data: Any) -> dict[str, Array]:
    """The predicate state of a batch held in one Data-like object: `data.xpos`, `.xmat`, `.site_xpos`,
    `.site_xmat`, `.qpos`, `.qvel`, `.contact.geom [N, C, 2]` and `.contact.dist [N, C]`, batched over N, which
    is what an `mjx.Data` stacked over environments holds (the MJX backend's call, under jit)."""
    contact = data.contact
    return gather_state(xp, index, const_pos, data.xpos, data.xmat, data.site_xpos, data.site_xmat, data.qpos,
                        contact.geom[..., 0], contact.geom[..., 1], contact.dist, data.qvel)


def mujoco_state(index: StateIndex, const_pos: np.ndarray, data: mujoco.MjData) -> dict[str, np.ndarray]:
    """The predicate state of one MuJoCo environment (N = 1), from `data` after a step."""
    ncon = data.ncon
    contact = data.contact
    return gather_state(
        np, index, const_pos[None], data.xpos[None], data.xmat[None], data.site_xpos[None], data.site_xmat[None],
        data.qpos[None], contact.geom1[None, :ncon], contact.geom2[None, :ncon], contact.dist[None, :ncon],
        data.qvel[None],
    )
