"""Emitting a sampled scene into one MuJoCo model with the MjSpec editing API.

The world is always built in the same order (physics options, background and floor, lighting, table and its
texture, robot, then objects in the instance's order), so the same SceneInstance gives the same model, element
for element. Structure depends only on which assets are present; poses, scales and colours are values, which
is what lets the batched backend put scenes of one task in one bucket.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco

from dojo.compiler.asset_emit import AssetHandles, add_asset, apply_background, apply_lighting, apply_table_texture
from dojo.compiler.rest_pose import rest_quat
from dojo.compiler.robot_emit import RobotHandles, add_robot, apply_physics
from dojo.compiler.scene_sample import SceneInstance
from dojo.compiler.spec_library import Spec, SpecLibrary

TABLE_ASSET = "table"


@dataclass
class EmittedScene:
    """The world spec and the names of what was put in it."""

    world: mujoco.MjSpec
    robot: RobotHandles
    objects: dict[str, AssetHandles]


def emit_scene(library: SpecLibrary, task: Spec, robot: Spec, scene: SceneInstance) -> EmittedScene:
    """Build the MjSpec of one sampled scene."""
    world = mujoco.MjSpec()
    world.modelname = f"{scene.task}-{scene.setting}-{scene.seed}"
    world.compiler.degree = False
    apply_physics(world, robot.data)
    world.visual.global_.offwidth = max(world.visual.global_.offwidth, 1280)
    world.visual.global_.offheight = max(world.visual.global_.offheight, 960)

    def asset(asset_id: str) -> Spec:
        return library.resolve(task, "asset", asset_id)[0]

    background = asset(scene.background)
    apply_background(world, background.data, base_dir=background.path.parent)
    apply_lighting(world, asset(scene.lighting).data)
    table = asset(TABLE_ASSET)
    add_asset(world, table.data, TABLE_ASSET, (0.0, 0.0, 0.0), base_dir=table.path.parent)
    texture = asset(scene.table_texture)
    apply_table_texture(world, texture.data, geoms=(f"{TABLE_ASSET}/top",), base_dir=texture.path.parent)
    robot_handles = add_robot(world, robot.data)
    objects: dict[str, AssetHandles] = {}
    for obj in scene.objects:
        spec = asset(obj.asset)
        objects[obj.name] = add_asset(world, spec.data, obj.name, obj.pos, rest_quat(obj.rest, obj.yaw_deg),
                                      obj.scale, obj.rgba, base_dir=spec.path.parent)
    return EmittedScene(world, robot_handles, objects)
