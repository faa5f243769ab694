"""Plans: everything one episode needs, compiled, content-addressed and self-contained.

A plan is what a backend loads and what a result names. It holds the compiled model (as MJCF text written by
MjSpec, meshes inline, so a plan file alone rebuilds the model), the initial state, cameras, instruction, the
success and score program as data and resolved against the scene (so a predicate naming something the scene does
not have fails here, located in the spec, and backends resolve nothing), the horizon, and `hash`: a SHA-256 over every input (the spec files' bytes,
the asset files they use, the compiler and MuJoCo versions, seed and setting). The hash is computed from the
inputs *before* compiling, so an unchanged plan is found in the cache without being rebuilt, and a changed asset
file changes exactly the hashes of the plans that could contain it.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import weakref
from dataclasses import asdict, dataclass, field
from importlib.metadata import version
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from dojo.backends.predicate_program import ProgramError, resolve_program
from dojo.backends.program_json import program_to_json
from dojo.backends.world_events import EventError, compile_events
from dojo.language.facts import FactError, resolve_facts

from dojo.compiler.actor_draws import draw_actors
from dojo.compiler.object_events import task_events
from dojo.compiler.horizon import task_horizon
from dojo.compiler.robot_emit import apply_home
from dojo.compiler.scene_emit import TABLE_ASSET, emit_scene
from dojo.compiler.scene_sample import (
    STANDARD_LOOK,
    LayoutError,
    SceneInstance,
    content_names,
    sample_scene,
    setting_config,
)
from dojo.compiler.plan_features import plan_features
from dojo.compiler.scene_settle import settle
from dojo.compiler.spec_errors import SpecError
from dojo.compiler.spec_library import Spec, SpecLibrary
from dojo.compiler.spec_schema import collect_marked

PLAN_FORMAT = "robodojo-plan/1"
COMPILER_REVISION = 4  # bump when emission changes in a way the versions below do not capture
# (2: scenes settle until at rest, and a layout whose objects slide or tip over while settling is redrawn;
#  3: plans carry their resolved predicate program, `compiled_program`;
#  4: plans list the simulator features they use, `requires`, and the compiler no longer takes a backend)
SETTLE_REDRAWS = 6     # layouts tried per episode before the compiler gives up (scene_settle)


@dataclass
class Plan:
    """One compiled episode. `model()` rebuilds the MjModel from `model_xml` (cached per Plan object)."""

    hash: str
    task: str
    dimension: str
    setting: str
    seed: int
    embodiment: str
    instruction: str
    horizon: int
    control_hz: float
    n_substeps: int
    cameras: list[str]
    robot: dict[str, Any]
    objects: dict[str, dict[str, Any]]
    regions: dict[str, dict[str, Any]]
    program: dict[str, Any]
    init_qpos: list[float]
    init_qvel: list[float]
    init_ctrl: list[float]
    model_xml: str
    scene: dict[str, Any] = field(default_factory=dict)
    settle: dict[str, Any] = field(default_factory=dict)
    """How the initial state was reached: `redraws` (layouts rejected first) and `seconds` simulated."""
    compiled_program: dict[str, Any] = field(default_factory=dict)
    """`program` resolved against this plan's model (`dojo.backends.program_json`)."""
    requires: list[str] = field(default_factory=list)
    """The simulator features the plan uses (`dojo.compiler.plan_features`): what a backend must support to run it."""
    format: str = PLAN_FORMAT

    @property
    def sort_key(self) -> str:
        """The plan's place among others wherever a choice follows an order (which plans pad and merge together,
        which body is a slot's template): task, setting and seed first, then the hash only to part plans that
        share those. The hash covers the compiler's and MuJoCo's versions, so ordering by it alone made two
        installs bucket the same episodes differently (the protocol's 1,150 plans made 47 buckets under MuJoCo
        4.0.1 and 46 under 4.0.0, 2026-12-03), and a kernel cache compiled by one missed modules the other needed."""
        return f"{self.task}\x1f{self.setting}\x1f{self.seed:+021d}\x1f{self.hash}"

    def model(self) -> mujoco.MjModel:
        """The plan's MjModel, compiled once per Plan object. Not a `functools.cached_property`: under Python 3.11
        its lock is one for all plans, so threads compiling many plans' models (MuJoCo lets go of the GIL while it
        compiles) took turns, where the protocol's 850 mjx plans take 8.9 s one after another on the 2-core CI
        machine. Two threads asking for one plan's model at once may both compile it; the first stored is kept."""
        model = self.__dict__.get("_model")
        if model is None:
            model = self.__dict__.setdefault("_model", mujoco.MjModel.from_xml_string(self.model_xml))
        return model

    def initial_data(self, model: mujoco.MjModel | None = None) -> mujoco.MjData:
        """A fresh MjData at the plan's initial state (forward kinematics done)."""
        model = model or self.model()
        data = mujoco.MjData(model)
        data.qpos[:] = self.init_qpos
        data.qvel[:] = self.init_qvel
        data.ctrl[:] = self.init_ctrl
        mujoco.mj_forward(model, data)
        return data

    def to_json(self) -> dict[str, Any]:
        return {k: v for k, v in asdict(self).items()}

    def save(self, path: Path) -> None:
        """Write atomically: a crash mid-write never leaves a truncated plan behind a valid index entry."""
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.to_json(), separators=(",", ":")))
        tmp.replace(path)

    @classmethod
    def load(cls, path: Path) -> "Plan":
        """The plan in file `path`: the object already loaded from it while anything still holds that one and the
        file is unchanged (`_LOADED`), else a fresh read."""
        stat = os.stat(path)
        key = (os.path.abspath(path), stat.st_ino, stat.st_mtime_ns, stat.st_size)
        plan = _LOADED.get(key)
        if plan is None:
            data = json.loads(Path(path).read_text())
            if data.get("format") != PLAN_FORMAT:
                raise ValueError(f"{path}: not a {PLAN_FORMAT} file (format {data.get('format')!r})")
            plan = _LOADED[key] = cls(**data)
        return plan


_LOADED: weakref.WeakValueDictionary[tuple[str, int, int, int], Plan] = weakref.WeakValueDictionary()
"""Plans read from files, by (absolute path, inode, modification time, size: `Plan.save` replaces a file, so a
rewritten plan is a new inode however quickly it follows), for as long as something holds them. A run
reads every plan twice otherwise: a batched backend loads the whole queue up front (`preload`), and the loop loads
each episode's plan again as it starts it. On an H200 host that second read was about 0.7 ms a plan, most of a
refill's time at 2,048 slots (every episode of a suite has its own plan); a shared object also keeps the model
`model()` built once. Loaded plans are read, never changed, so sharing one object is safe."""


@functools.cache
def compiler_id() -> str:
    """What, besides the spec inputs, determines a compiled plan (cached: reading the installed version parses the
    package's metadata, once per plan hash before)."""
    return f"robodojo {version('robodojo')} rev {COMPILER_REVISION}; mujoco {mujoco.__version__}"


def _stamp(path: Path) -> tuple[str, int, int]:
    """A file's identity for the digest caches: its path, modification time and size (as the spec library's own
    cache of parsed files)."""
    stat = path.stat()
    return str(path), stat.st_mtime_ns, stat.st_size


_RELPATHS: dict[tuple[str, tuple[str, int, int]], tuple[str, ...]] = {}
"""(kind, file stamp) -> the files a spec of that file names: one entry per spec file version a process reads."""


def _relpaths(spec: Spec, stamp: tuple[str, int, int]) -> tuple[str, ...]:
    """The files a spec names (its `x-relpath` values, sorted), found once per version of its file: finding them
    walks the data beside its schema, which every plan of a suite repeated for the same few specs."""
    key = (spec.kind, stamp)
    if key not in _RELPATHS:
        _RELPATHS[key] = tuple(sorted(str(use.value) for use in collect_marked(spec.kind, spec.data, "x-relpath")))
    return _RELPATHS[key]


@functools.lru_cache(maxsize=4096)
def _digest_of(stamps: tuple[tuple[str, int, int], ...], relpaths: tuple[str, ...]) -> str:
    """`_spec_digest` of the files behind `stamps` (the spec's, then each named file's), read only when one of
    them changed: each plan hash re-read and re-hashed the spec's meshes and textures before."""
    h = hashlib.sha256(Path(stamps[0][0]).read_bytes())
    for rel, (path, _, _) in zip(relpaths, stamps[1:]):
        h.update(rel.encode())
        h.update(Path(path).read_bytes())
    return h.hexdigest()


def _spec_digest(spec: Spec) -> str:
    """Hash of a spec file and every file it names, by path relative to its package (same in a wheel)."""
    stamp = _stamp(spec.path)
    relpaths = _relpaths(spec, stamp)
    return _digest_of((stamp, *(_stamp(spec.path.parent / rel) for rel in relpaths)), relpaths)


def input_specs(library: SpecLibrary, task: Spec, setting: str) -> list[Spec]:
    """Every spec a plan of (task, setting) may read: the task, its robot, the table, each object's candidate
    assets, the presets the setting may draw, and the clutter set when the setting has clutter."""
    cfg = setting_config(task.data, setting)
    specs = [task, library.resolve(task, "robot", task.data["embodiment"])[0]]
    specs += library.resolve(task, "asset", TABLE_ASSET)
    for entry in task.data["scene"].get("fixtures", []) + task.data["scene"]["objects"]:
        specs += library.resolve(task, "asset", entry["asset"])
        if cfg["instances"] and "variants" in entry:
            specs += library.resolve(task, "asset", entry["variants"])
        for ref in entry.get("draw_from", []):
            specs += library.resolve(task, "asset", ref)
    for key in STANDARD_LOOK:
        if setting == "standard" and key not in task.data.get("settings", {}).get("standard", {}):
            specs += library.resolve(task, "asset", STANDARD_LOOK[key])
        else:
            specs += library.resolve(task, "asset", cfg.get(key, STANDARD_LOOK[key]))
    if cfg["clutter"][1] > 0:
        specs += library.resolve(task, "asset", {"set": "clutter"})
    return list({(s.kind, s.id): s for s in specs}.values())


def plan_hash(library: SpecLibrary, task: Spec, setting: str, seed: int,
              demo_lengths: list[int] | None = None) -> str:
    """The content hash of the plan of (task, setting, seed), from its inputs alone (the horizon included, since
    an `auto` horizon depends on the task's demos)."""
    h = hashlib.sha256(compiler_id().encode())
    for spec in sorted(input_specs(library, task, setting), key=lambda s: (s.kind, s.id)):
        h.update(f"{spec.kind}:{spec.id}:{_spec_digest(spec)}".encode())
    horizon = task_horizon(task.data, demo_lengths)
    h.update(json.dumps({"setting": setting, "seed": seed, "horizon": horizon}).encode())
    return h.hexdigest()


def compile_plan(library: SpecLibrary, task: Spec, setting: str, seed: int, *,
                 demo_lengths: list[int] | None = None) -> Plan:
    """Sample, emit, compile and settle one episode into a Plan. `demo_lengths` set an `auto` horizon."""
    digest = plan_hash(library, task, setting, seed, demo_lengths)
    robot = library.resolve(task, "robot", task.data["embodiment"])[0]
    for redraw in range(SETTLE_REDRAWS):
        scene: SceneInstance = sample_scene(library, task, setting, seed, redraw)
        emitted = emit_scene(library, task, robot, scene)
        model = emitted.world.compile()
        data = mujoco.MjData(model)
        apply_home(model, data, emitted.robot)
        settled = settle(model, data, {n: h.body for n, h in emitted.objects.items() if h.free_joint},
                         frozenset(content_names(task.data["scene"])))
        if settled.ok:
            break
    else:
        what = "; ".join(f"{n}: {d}" for n, d in settled.disturbed.items()) or "objects still moving"
        raise LayoutError([task.problem(("scene",), f"none of {SETTLE_REDRAWS} layouts of setting {setting}, seed "
                                        f"{seed} settled with the robot at home (the last after "
                                        f"{settled.seconds:.1f} s: {what})")])
    objects = {}
    for obj in scene.objects:
        handles = asdict(emitted.objects[obj.name])
        objects[obj.name] = {**handles, "group": obj.group, "color": obj.color, "clutter": obj.clutter,
                             "fixed": obj.fixed, "half_extents": obj.half_extents, "attributes": obj.attributes}
    regions = {name: {"center": r["center"], "size": r["size"], "on": r.get("on")}
               for name, r in task.data["scene"].get("regions", {}).items()}
    events = task_events(task.data)  # the spec's events and those its objects write (`hidden_after`)
    try:  # facts (the number on a drawn card) become this episode's values: backends see plain predicates
        program = resolve_facts({"success": task.data["success"], "stages": task.data.get("stages", []),
                                 "stage_order": task.data.get("stage_order", "any"),
                                 "events": events,
                                 "actors": draw_actors(task.data.get("actors", []), task.id, setting, seed)}, objects)
    except FactError as exc:
        raise SpecError([task.problem(exc.path, str(exc))]) from None
    plan = Plan(
        hash=digest, task=task.id, dimension=task.data["dimension"], setting=setting, seed=seed,
        embodiment=robot.id, instruction=scene.instruction, horizon=task_horizon(task.data, demo_lengths),
        control_hz=emitted.robot.control_hz, n_substeps=emitted.robot.n_substeps,
        cameras=list(emitted.robot.cameras), robot=asdict(emitted.robot), objects=objects, regions=regions,
        program=program, init_qpos=_floats(data.qpos), init_qvel=_floats(data.qvel), init_ctrl=_floats(data.ctrl),
        model_xml=emitted.world.to_xml(), scene=scene.to_json(),
        settle={"redraws": redraw, "seconds": round(settled.seconds, 3)},
        requires=plan_features(model, {**task.data, "events": events}),
    )
    try:
        plan.compiled_program = program_to_json(resolve_program(plan))
        compile_events(plan, plan.model())
    except ProgramError as exc:
        raise SpecError([task.problem(exc.path or ("success",), str(exc))]) from None
    except EventError as exc:
        raise SpecError([task.problem(exc.path, str(exc))]) from None
    return plan


def _floats(array: np.ndarray) -> list[float]:
    return [float(x) for x in array]
