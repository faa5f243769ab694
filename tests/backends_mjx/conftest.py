"""Small synthetic plans for the MJX tests: real plans (two 6-DoF arms, hull meshes) take minutes to compile for
CPU, so the CI tests use scenes of a few spheres and boxes that keep the structure that matters here: a task
object, an actuated joint, and a varying number of clutter bodies of two kinds in the `random` setting; `items` adds
task objects of those kinds, so that tasks differ in their objects (merged buckets)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest

from dojo.compiler.plan import Plan

TEST_ASSETS = Path(__file__).resolve().parents[1] / "specs" / "pack" / "assets"
CACHE_DIR = os.environ.get("DOJO_TEST_JAX_CACHE", os.path.join(os.path.expanduser("~"), ".cache", "dojo-test-jax"))


def _clutter(name: str, kind: str, x: float, size: float, y: float = 0.3) -> str:
    geom = (f'<geom name="{name}/g0" type="sphere" size="{size}" mass="0.05"/>' if kind == "ball"
            else f'<geom name="{name}/g0" type="box" size="{size} {size} {size}" mass="0.05"/>')
    return (f'<body name="{name}" pos="{x} {y} {size}"><joint name="{name}/free" type="free"/>{geom}'
            f'<site name="{name}/top" size="{size / 4}"/></body>')


def toy_plan(task: str = "toy", setting: str = "standard", seed: int = 0,
             clutter: tuple[str, ...] = (), block_size: float = 0.03, rgba: str = "0.8 0.1 0.1 1",
             items: tuple[str, ...] = (), fixture_y: float | None = None) -> Plan:
    """A plan of a tiny scene: floor, a slider pushing a free box, optional free task items and clutter bodies;
    `fixture_y`: a wall welded to the world there (a fixture, such as a task's power strip)."""
    bodies = "".join(_clutter(f"item_{k}", kind, 0.3 - 0.15 * k, 0.025, y=-0.3) for k, kind in enumerate(items))
    if fixture_y is not None:
        bodies += (f'<body name="wall" pos="0.1 {fixture_y} 0.05">'
                   '<geom name="wall/g0" type="box" size="0.2 0.02 0.05"/></body>')
    bodies += "".join(_clutter(f"clutter_{k}", kind, -0.3 + 0.15 * k, 0.02 + 0.005 * seed % 3)
                     for k, kind in enumerate(clutter))
    xml = f"""<mujoco model="{task}-{setting}-{seed}">
  <option timestep="0.004"/>
  <worldbody>
    <light name="light/key" pos="0 0 2"/>
    <geom name="floor" type="plane" size="2 2 0.1"/>
    <body name="pusher" pos="-0.3 0 0.05"><joint name="slide" type="slide" axis="1 0 0" range="-0.5 0.5"/>
      <geom name="pusher/g0" type="box" size="0.03 0.03 0.03" mass="1"/></body>
    <body name="block" pos="{0.1 + 0.01 * seed} 0 {block_size}"><joint name="block/free" type="free"/>
      <geom name="block/g0" type="box" size="{block_size} {block_size} {block_size}" rgba="{rgba}" mass="0.1"/>
    </body>
    {bodies}
  </worldbody>
  <actuator><position name="push" joint="slide" kp="200" kv="20" ctrlrange="-0.5 0.5"/></actuator>
</mujoco>"""
    import mujoco

    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    objects: dict[str, dict[str, Any]] = {"block": {"body": "block", "clutter": False}}
    objects.update({f"item_{k}": {"body": f"item_{k}", "clutter": False} for k in range(len(items))})
    objects.update({f"clutter_{k}": {"body": f"clutter_{k}", "clutter": True} for k in range(len(clutter))})
    return Plan(hash=f"{task}-{setting}-{seed}", task=task, dimension="generalization", setting=setting, seed=seed,
                embodiment="toy", instruction="push", horizon=20, control_hz=25.0, n_substeps=10, cameras=[],
                robot={}, objects=objects, regions={}, program={}, init_qpos=[float(x) for x in data.qpos],
                init_qvel=[0.0] * model.nv, init_ctrl=[0.0] * model.nu, model_xml=xml)


@pytest.fixture(scope="session", autouse=True)
def jax_cache() -> None:
    """A persistent compilation cache, so that repeated test runs skip XLA compilation."""
    from dojo.backends.mjx.cache import enable_compilation_cache

    enable_compilation_cache(CACHE_DIR)


def forward_hooks() -> Any:
    """Engine hooks whose refresh after the sub-steps is the MJX backend's under Warp (`_DeviceHooks.refresh`): a
    whole forward, against which the lanes' lighter refresh (`streams.refresh`) is compared."""
    from mujoco import mjx

    from dojo.backends.mjx.batch import Hooks

    class ForwardHooks(Hooks):
        def refresh(self, m: Any, d: Any) -> Any:
            return mjx.forward(m, d)

    return ForwardHooks()


def write_pack(root: Path, tasks: dict[str, str], suites: dict[str, str]) -> Path:
    """A task pack under `root/pack`: the given task and suite files (name -> YAML text) beside the test pack's
    assets (its block and plate), for `dojo run packs=[...]` in a child process."""
    pack = root / "pack"
    for folder, files in {"tasks": tasks, "suites": suites}.items():
        (pack / folder).mkdir(parents=True)
        for name, text in files.items():
            (pack / folder / name).write_text(text)
    (pack / "assets").mkdir()
    for asset in TEST_ASSETS.iterdir():
        (pack / "assets" / asset.name).write_text(asset.read_text())
    return pack
