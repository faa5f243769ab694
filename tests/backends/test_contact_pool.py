"""Contacts of a whole batch kept in one pool (MuJoCo Warp's layout) give the same per-environment contact matrix
as per-environment rows (MuJoCo's and MJX jax's layout), in NumPy and under jax.jit."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dojo.backends.predicates import contact_matrix, pool_contact_matrix

N_ATOMS = 3
GEOM_ATOM = np.asarray([0, 1, 2, N_ATOMS, 1])
"""Five geoms: atoms 0, 1, 2, an untracked geom, and a second geom of atom 1."""


def _random_pool(rng: np.random.Generator, worlds: int, rows: int, filled: int):
    """A pool of `rows` rows whose first `filled` are live; the rest hold stale contacts a real pool keeps."""
    geom = rng.integers(0, len(GEOM_ATOM), (rows, 2))
    dist = np.where(rng.random(rows) < 0.6, -0.001, 0.01)
    worldid = rng.integers(0, worlds, rows)
    return geom, dist, worldid, np.asarray([filled])


def _per_world_rows(geom, dist, worldid, filled, worlds):
    """The same live contacts laid out per environment, padded with far rows (MJX jax's inactive rows)."""
    live = [[k for k in range(int(filled[0])) if worldid[k] == w] for w in range(worlds)]
    width = max(1, max(len(rows) for rows in live))
    g1, g2 = np.zeros((worlds, width), int), np.zeros((worlds, width), int)
    d = np.full((worlds, width), 1.0)
    for w, rows in enumerate(live):
        g1[w, :len(rows)], g2[w, :len(rows)], d[w, :len(rows)] = geom[rows, 0], geom[rows, 1], dist[rows]
    return g1, g2, d


@pytest.mark.parametrize("seed", range(5))
def test_pool_gives_the_per_world_matrix(seed):
    rng = np.random.default_rng(seed)
    worlds = 4
    geom, dist, worldid, filled = _random_pool(rng, worlds, rows=40, filled=25)
    expected = contact_matrix(np, GEOM_ATOM, *_per_world_rows(geom, dist, worldid, filled, worlds), N_ATOMS)
    got = pool_contact_matrix(np, GEOM_ATOM, geom, dist, worldid, filled, worlds, N_ATOMS)
    jitted = jax.jit(pool_contact_matrix, static_argnums=(0, 6, 7))(
        jnp, jnp.asarray(GEOM_ATOM), jnp.asarray(geom), jnp.asarray(dist, jnp.float32), jnp.asarray(worldid),
        jnp.asarray(filled), worlds, N_ATOMS)
    assert got.shape == (worlds, N_ATOMS, N_ATOMS) and got.dtype == bool
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(np.asarray(jitted), expected)
    assert expected.any() and not expected.all()  # the draw exercises both answers


def test_stale_rows_far_contacts_and_foreign_worlds_are_ignored():
    geom = np.asarray([[0, 1], [1, 2], [0, 2], [4, 0], [0, 3]])
    dist = np.asarray([-0.002, 0.003, -0.001, -0.001, -0.001])
    worldid = np.asarray([1, 0, 7, 0, 0])  # row 2 names a world outside the batch of 2
    filled = np.asarray([4])  # row 4 is stale
    got = pool_contact_matrix(np, GEOM_ATOM, geom, dist, worldid, filled, 2, N_ATOMS)
    expected = np.zeros((2, N_ATOMS, N_ATOMS), bool)
    expected[1, 0, 1] = expected[1, 1, 0] = True  # row 0: world 1, atoms 0-1 touching
    expected[0, 1, 0] = expected[0, 0, 1] = True  # row 3: world 0, geom 4 is atom 1; row 1 is 3 mm apart
    np.testing.assert_array_equal(got, expected)


def test_an_empty_pool_touches_nothing():
    empty = np.zeros((0, 2), int)
    got = pool_contact_matrix(np, GEOM_ATOM, empty, np.zeros(0), np.zeros(0, int), np.asarray([0]), 3, N_ATOMS)
    assert got.shape == (3, N_ATOMS, N_ATOMS) and not got.any()
