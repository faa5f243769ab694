"""What the tick reads after the sub-steps (`_DeviceHooks.refresh`) equals what a full `mjx.forward` gives for it.

The backend's hooks refresh poses and tendons only (a full forward was a second copy of the physics in the traced
program); the predicates and proprioception read body and site poses, tendon lengths and speeds, and the contacts
the last sub-step found. On a small model with a free body, a site and a fixed tendon (the grippers' kind), each of
those equals the full forward's at a moving state.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

XML = """<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 0.1"/>
    <body name="arm" pos="0 0 0.2"><joint name="a" type="hinge" axis="0 1 0"/><geom type="capsule" size="0.02 0.1"/>
      <body name="finger" pos="0.1 0 0"><joint name="b" type="slide" axis="1 0 0" range="0 0.05"/>
        <geom type="box" size="0.01 0.01 0.01"/><site name="tip" pos="0.02 0 0"/></body></body>
    <body name="box" pos="0.3 0 0.05"><joint type="free"/><geom type="box" size="0.03 0.03 0.03"/></body>
  </worldbody>
  <tendon><fixed name="grip"><joint joint="a" coef="0.5"/><joint joint="b" coef="-1"/></fixed></tendon>
</mujoco>"""


def test_refresh_gives_the_poses_and_tendons_a_full_forward_gives() -> None:
    from dojo.backends.mjx.backend import _DeviceHooks

    model = mujoco.MjModel.from_xml_string(XML)
    mx = mjx.put_model(model, impl="jax")
    qpos = np.asarray(model.qpos0, np.float32).copy()
    qpos[:2] = (0.3, 0.02)
    qpos[2:5] += (0.05, -0.02, 0.01)
    qvel = np.linspace(-0.5, 0.7, model.nv).astype(np.float32)
    d = mjx.make_data(model, impl="jax").replace(qpos=jnp.asarray(qpos), qvel=jnp.asarray(qvel))
    hooks = _DeviceHooks({}, {}, "jax")
    full, light = jax.jit(mjx.forward)(mx, d), jax.jit(hooks.refresh)(mx, d)  # jitted: eager dispatch is slower
    for name in ("xpos", "xmat", "site_xpos", "site_xmat", "ten_length"):
        np.testing.assert_allclose(np.asarray(getattr(light, name)), np.asarray(getattr(full, name)), atol=1e-6,
                                   err_msg=name)
    np.testing.assert_allclose(np.asarray(light._impl.ten_velocity), np.asarray(full._impl.ten_velocity), atol=1e-6)
    assert float(np.abs(np.asarray(full._impl.ten_velocity)).max()) > 0.05  # the speeds are not trivially zero
    assert not np.allclose(np.asarray(light.xpos), np.asarray(d.xpos))  # the poses were really recomputed
