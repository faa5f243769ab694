"""A control step's sub-steps as one Warp call (`substeps`) step exactly the physics of one `mjx.step` per
sub-step, on Warp's CPU device: the same kernels on the same buffers, so the states must be equal bit for bit."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from dojo.backends.mjx.cache import graph_mode, warp_installed
from dojo.backends.mjx.substeps import substeps

XML = """<mujoco><option timestep="0.002"/><worldbody><geom type="plane" size="1 1 .1"/>
<body pos="0 0 .06"><freejoint/><geom name="box" type="box" size=".05 .05 .05"/></body>
<body pos=".03 0 .17"><freejoint/><geom type="sphere" size=".04"/></body>
<body pos="-.2 0 .1"><joint type="hinge" axis="0 1 0"/><geom type="capsule" size=".02" fromto="0 0 0 .1 0 0"/></body>
</worldbody></mujoco>"""


@pytest.fixture(scope="module")
def warp_batch() -> tuple:
    if not warp_installed():
        pytest.skip("needs warp-lang (pip install 'robodojo[warp]')")
    model = mujoco.MjModel.from_xml_string(XML)
    mx = mjx.put_model(model, impl="warp", graph_mode=graph_mode(None, "warp"))
    empty = mjx.make_data(model, impl="warp", naconmax=256, njmax=128)
    batch = 4
    data = jax.vmap(lambda i: empty.replace(qpos=empty.qpos.at[0].add(0.01 * i)))(jnp.arange(batch))
    box = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "box")
    # A per-environment model field, as a bucket's members have: the box's size differs in every world.
    sizes = jnp.stack([mx.geom_size.at[box].mul(1.0 + 0.2 * i) for i in range(batch)])
    in_axes = jax.tree.map(lambda _: None, mx).tree_replace({"geom_size": 0})
    return mx.tree_replace({"geom_size": sizes}), data, in_axes


def test_one_warp_call_steps_exactly_as_one_call_per_substep(warp_batch: tuple) -> None:
    m, data, in_axes = warp_batch
    n = 7
    one_each = jax.jit(lambda d: jax.lax.fori_loop(
        0, n, lambda _, x: jax.vmap(mjx.step, in_axes=(in_axes, 0))(m, x), d))
    together = jax.jit(lambda d: substeps("warp", n, in_axes)(m, d))
    for _ in range(4):  # resting on the floor (each world its own box size), the sphere falling onto it
        a, b = one_each(data), together(data)
        for field in ("qpos", "qvel", "time"):
            np.testing.assert_array_equal(np.asarray(getattr(a, field)), np.asarray(getattr(b, field)))
        data = a
    assert np.ptp(np.asarray(data.qpos)[:, 2]) > 0  # the worlds differ: the batch really is per environment
    assert np.asarray(data._impl.nacon).max() > 0    # and the steps compared include contacts


def test_the_count_of_substeps_is_the_count_of_steps(warp_batch: tuple) -> None:
    """`n` is honoured, not one step per call: 3 then 2 sub-steps are 5."""
    m, data, in_axes = warp_batch
    five = jax.jit(lambda d: substeps("warp", 5, in_axes)(m, d))(data)
    three_two = jax.jit(lambda d: substeps("warp", 2, in_axes)(m, substeps("warp", 3, in_axes)(m, d)))(data)
    np.testing.assert_array_equal(np.asarray(five.qpos), np.asarray(three_two.qpos))
    np.testing.assert_allclose(np.asarray(five.time), 5 * 0.002, rtol=1e-6)


def test_a_control_step_needs_a_physics_step() -> None:
    with pytest.raises(ValueError, match="at least one physics step"):
        substeps("jax", 0, None)
