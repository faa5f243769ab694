"""A thread (an asset's `threads:`, a joint equality coupling a hinge to a slide) simulated by MJX as by CPU MuJoCo:
the threaded nut alone, a torque on its hinge for half a second, the same turn and sink on both (about a minute,
most of it XLA compiling the 250 steps on the CPU: `-m slow`)."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from dojo.compiler.asset_emit import add_asset
from dojo.compiler.spec_library import SpecLibrary

pytestmark = pytest.mark.slow

STEPS, TORQUE = 250, 0.1


def test_mjx_turns_and_sinks_a_thread_as_the_cpu_backend_does():
    import jax
    from mujoco import mjx

    library = SpecLibrary.load([], strict=False)
    asset = library.get("asset", "threaded_nut")
    spec = mujoco.MjSpec()
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    add_asset(spec, asset.data, "nut", [0.0, 0.0, 0.0], base_dir=asset.path.parent)
    model = spec.compile()
    hinge, slide = model.joint("nut/thread"), model.joint("nut/advance")
    data = mujoco.MjData(model)
    data.qfrc_applied[hinge.dofadr[0]] = TORQUE
    mujoco.mj_step(model, data, STEPS)
    cpu = data.qpos[[hinge.qposadr[0], slide.qposadr[0]]]
    assert cpu[0] > 1.0 and cpu[1] == pytest.approx(cpu[0] * 0.008 / (2 * np.pi), rel=0.1)

    m = mjx.put_model(model)
    d = mjx.put_data(model, mujoco.MjData(model))
    d = d.replace(qfrc_applied=d.qfrc_applied.at[hinge.dofadr[0]].set(TORQUE))
    d = jax.jit(lambda x: jax.lax.fori_loop(0, STEPS, lambda _, y: mjx.step(m, y), x))(d)
    on_mjx = np.asarray(d.qpos)[[hinge.qposadr[0], slide.qposadr[0]]]
    assert np.allclose(on_mjx, cpu, rtol=1e-4, atol=1e-6)
