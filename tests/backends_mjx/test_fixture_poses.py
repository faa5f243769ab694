"""Fixtures that differ between a bucket's members sit where each environment's plan puts them, under MuJoCo
Warp too, which computes the poses of geoms welded to the world once, in `make_data`, and never again. Before the
bucket table carried every member's geom poses, every environment of a bucket collided with member 0's fixtures:
on the GPU the oracle then failed `plug_in_charger`, `fasten_screws` and `pour_balls_into_vase` episodes that it
solves alone."""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest
from conftest import toy_plan

from dojo.backends.mjx.batch import Engine
from dojo.backends.mjx.bucket import Member, make_buckets
from dojo.backends.mjx.cache import warp_installed

WALLS = (0.25, -0.15, 0.05)


@pytest.fixture(scope="module")
def engine() -> Engine:
    if not warp_installed():
        pytest.skip("needs warp-lang (pip install 'robodojo[warp]'): the bug and the fix are MuJoCo Warp's")
    buckets = make_buckets([toy_plan(seed=k, fixture_y=y) for k, y in enumerate(WALLS)])
    assert len(buckets) == 1 and "body_pos" in buckets[0].varying  # one structure, the wall's place per member
    return Engine(buckets, [4], "warp")


def _cpu_wall(plan_model: mujoco.MjModel) -> np.ndarray:
    data = mujoco.MjData(plan_model)
    mujoco.mj_kinematics(plan_model, data)
    return data.geom_xpos[mujoco.mj_name2id(plan_model, mujoco.mjtObj.mjOBJ_GEOM, "wall/g0")].copy()


def test_each_environment_has_its_own_members_fixture_after_resets_and_refills(engine: Engine) -> None:
    arr = engine.arrays[0]
    wall = mujoco.mj_name2id(arr.bucket.model, mujoco.mjtObj.mjOBJ_GEOM, "wall/g0")
    expected = [_cpu_wall(m.model) for m in arr.bucket.members]
    ctrl = [np.zeros((4, arr.bucket.model.nu), np.float32)]
    for members in (np.asarray([2, 1, 0, 1]), np.asarray([0, 2, 1, 2])):  # the load, then every slot refilled
        engine.tick([members], [np.ones(4, bool)], [np.zeros(4, bool)], ctrl)
        engine.tick([members], [np.zeros(4, bool)], [np.ones(4, bool)], ctrl)  # a step: kinematics ran
        got = np.asarray(engine.data[0].geom_xpos)[:, wall]
        for env, member in enumerate(members):
            np.testing.assert_allclose(got[env], expected[member], atol=1e-6)
        assert len({round(float(y), 3) for y in got[:, 1]}) == len(set(members.tolist()))


def test_the_tables_geom_poses_are_each_members_own_mocap_included() -> None:
    """`Bucket.geom_poses` computes every member's poses with one MjData, reset to each member's model in turn: a
    fixture (the wall) and a kinematic (mocap) body must sit where each member's own model puts them, whatever
    member came before."""
    lift = '<body name="lift" mocap="true" pos="0.4 {y} 0.3"><geom name="lift/g0" type="sphere" size="0.02"/></body>'
    plans = [toy_plan(seed=k, fixture_y=y) for k, y in enumerate(WALLS)]
    plans = [dataclasses.replace(p, model_xml=p.model_xml.replace('<body name="wall"', lift.format(y=0.1 * k)
                                                                  + '<body name="wall"'))
             for k, p in enumerate(plans)]
    bucket = make_buckets(plans)[0]
    assert len(bucket.members) == 3 and bucket.model.nmocap == 1
    at = mujoco.mj_name2id(bucket.model, mujoco.mjtObj.mjOBJ_GEOM, "lift/g0")

    def fresh(member: Member) -> tuple[np.ndarray, np.ndarray]:
        data = mujoco.MjData(member.model)
        data.qpos[:] = member.qpos
        mujoco.mj_kinematics(member.model, data)
        return data.geom_xpos.copy(), data.geom_xmat.reshape(-1, 3, 3).copy()

    for members in (list(bucket.members), list(bucket.members)[::-1]):
        bucket.members[:] = members
        positions, rotations = bucket.geom_poses()
        for k, member in enumerate(members):
            want_pos, want_rot = fresh(member)
            np.testing.assert_array_equal(positions[k], want_pos)
            np.testing.assert_array_equal(rotations[k], want_rot)
        assert len({round(float(y), 3) for y in positions[:, at, 1]}) == 3  # each member's own lift
