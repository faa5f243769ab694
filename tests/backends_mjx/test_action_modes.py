"""The mjx backend compiles only the action modes its policy sends: without an ee mode its tick holds no IK (most
of the tick's XLA program under Warp), joint actions give the same controls either way, and a mode it was not
built for is refused with a message that names the fix."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dojo.backends.mjx import backend as B
from dojo.backends.mjx.batch import _initial_data, _prepare
from dojo.backends.mjx.bucket import make_buckets
from dojo.backends.mjx.lanes import bucket_programs
from dojo.backends.mjx.sharding import Placement
from dojo.backends.mujoco.kinematics import RobotIndex
from dojo.compiler.plan import compile_plan
from dojo.compiler.spec_library import SpecLibrary

N = 3


@pytest.fixture(scope="module")
def bucket():
    library = SpecLibrary.load(strict=False)
    return make_buckets([compile_plan(library, library.get("task", "stack_blocks"), "standard", 0)])[0]


def _control(bucket, ik: bool):
    """The hooks' control step of one bucket, jitted, and its arguments."""
    hooks = B._DeviceHooks({bucket.key: bucket_programs(bucket)},
                           {bucket.key: RobotIndex.build(bucket.model, bucket.members[0].plan.robot)}, "jax", ik=ik)
    arr = _prepare(bucket, N, "jax", Placement.over(None, "jax"))
    data = _initial_data(arr, "jax")
    rng = np.random.default_rng(0)
    actions = jnp.asarray(rng.uniform(-0.3, 0.3, (N, B.INPUT_WIDTH)), jnp.float32)
    modes = jnp.asarray([B.MODES.index("joint"), B.DELTA_JOINT, B.MODES.index("joint")], jnp.int32)
    fn = jax.jit(lambda m, d, a, k: hooks.control(arr, m, d, (a, k)))
    return fn, (arr.mx, data, actions, modes)


def test_joint_only_ticks_hold_no_ik_and_drive_the_same_controls(bucket):
    with_ik, args = _control(bucket, ik=True)
    without, _ = _control(bucket, ik=False)
    size_ik, size = len(with_ik.lower(*args).as_text()), len(without.lower(*args).as_text())
    assert size < 0.2 * size_ik, (size, size_ik)
    (ctrl_ik, clipped_ik), (ctrl, clipped) = with_ik(*args), without(*args)
    np.testing.assert_array_equal(np.asarray(ctrl), np.asarray(ctrl_ik))
    np.testing.assert_array_equal(np.asarray(clipped), np.asarray(clipped_ik))


def test_modes_are_checked_when_built_and_refused_when_not_built():
    with pytest.raises(ValueError, match=r"unknown action modes \['joints'\]"):
        B.MjxBackend(impl="jax", action_modes=("joints",))
    backend = B.MjxBackend(impl="jax", action_modes=("joint",))
    with pytest.raises(ValueError, match=r"built for action modes \['joint'\], not 'ee'.*BackendOptions.action_modes"):
        backend.step(np.zeros((0, 16), np.float32), mode="ee")
