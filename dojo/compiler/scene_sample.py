"""Sampling one scene of a task: (task spec, setting, episode seed) -> SceneInstance.

Everything random about an episode is decided here and nowhere else, from one PCG64 stream seeded by a hash of
(task id, setting, seed): the same inputs give the same instance on any machine and any Python, and a change to
one task never shifts the scenes of another. Placement is rejection sampling of footprint circles inside the
placement regions, with a bounded number of tries; a layout that cannot be placed fails with an error that names
the region and the objects that did not fit, never with a silently overlapping scene.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from dojo.compiler.asset_geometry import asset_bounds
from dojo.compiler.rest_pose import rested_box
from dojo.compiler.robot_emit import TABLE_HALF_SIZE, TABLE_TOP_Z
from dojo.compiler.spec_errors import SpecError
from dojo.compiler.spec_library import Spec, SpecLibrary

SETTINGS = ("standard", "random")
TRIES_PER_OBJECT = 200
LAYOUT_RESTARTS = 20
ASSET_REDRAWS = 5
TABLE_MARGIN = 0.04  # keep objects this far from the table edge
ROBOT_STRIP_Y = -0.28  # the near edge up to here holds the arms' bases: clutter goes beyond it
# The fixed look of the standard setting; the random setting draws from every preset of each class.
STANDARD_LOOK = {"lighting": "bright_studio", "background": "studio_grey", "table_texture": "wood_light"}
RANDOM_DEFAULTS: dict[str, Any] = {"clutter": [0, 25], "lighting": {"class": "lighting"},
                                   "background": {"class": "background"}, "table_texture": {"class": "texture"},
                                   "instances": True, "colors": True}
STANDARD_DEFAULTS: dict[str, Any] = {"clutter": [0, 0], "instances": False, "colors": False}
NAMED_COLORS = {
    "red": (0.85, 0.12, 0.1, 1.0), "green": (0.15, 0.65, 0.2, 1.0), "blue": (0.12, 0.3, 0.85, 1.0),
    "yellow": (0.95, 0.8, 0.1, 1.0), "orange": (0.95, 0.5, 0.1, 1.0), "purple": (0.55, 0.2, 0.7, 1.0),
    "pink": (0.95, 0.45, 0.65, 1.0), "white": (0.92, 0.92, 0.92, 1.0), "black": (0.08, 0.08, 0.08, 1.0),
    "brown": (0.45, 0.28, 0.12, 1.0), "grey": (0.5, 0.5, 0.5, 1.0), "cyan": (0.1, 0.75, 0.8, 1.0),
}


CONTENT_GAP = 0.002
"""Room (m) between objects put inside a container, and between them and its `inside` box (they settle into it)."""
CONTENT_JITTER = 0.15
"""Random turn (rad) of each object put inside a container about the container's axis, so scenes differ."""


def content_names(scene: dict) -> set[str]:
    """The names of the objects the compiler puts inside a container (`inside`), `count` expanded."""
    return {name for entry in scene.get("objects", []) if "inside" in entry for name in instance_names(entry)}


def instance_names(entry: dict) -> list[str]:
    """The names of an object entry's copies: its name, or name_0, name_1, ... with `count`."""
    count = entry.get("count", 1)
    return [entry["name"]] if count == 1 else [f"{entry['name']}_{i}" for i in range(count)]


class LayoutError(SpecError):
    """The task's objects do not fit their regions (after the bounded number of tries)."""


@dataclass
class PlacedObject:
    """One object of the sampled scene, with everything the emitter needs and the predicates may ask."""

    name: str
    asset: str
    pos: list[float]            # world position of the asset frame (upright: centre of its footprint, on its support)
    yaw_deg: float
    scale: float
    color: str | None
    rgba: list[float] | None
    fixed: bool                 # a fixture (placed first, never moved by the sampler)
    group: str | None = None
    clutter: bool = False
    attributes: dict[str, Any] = field(default_factory=dict)
    # Half extents [hx, hy, hz] of the scaled asset's box, in its rest pose, about its footprint's centre (upright:
    # its frame's vertical axis); it spans 2 hz up from its support (for predicates and skills).
    half_extents: list[float] = field(default_factory=list)
    rest: str = "upright"       # how it lies on its support before the yaw (`dojo.compiler.rest_pose`)


@dataclass
class SceneInstance:
    """A fully sampled episode scene: pure data, hashable, and the only input of emission besides the specs."""

    task: str
    setting: str
    seed: int
    instruction: str
    slots: dict[str, str]
    objects: list[PlacedObject]
    lighting: str
    background: str
    table_texture: str
    clutter_requested: int

    def to_json(self) -> dict:
        """The instance as plain data; an upright object's record leaves out `rest`, as it was before objects could
        lie, so scenes of standing objects keep their digests."""
        data = asdict(self)
        for obj in data["objects"]:
            if obj["rest"] == "upright":
                del obj["rest"]
        return data

    def digest(self) -> str:
        """A stable hash of the instance (floats rounded to 1e-9 m), for golden tests and plan provenance."""
        return hashlib.sha256(json.dumps(_rounded(self.to_json()), sort_keys=True).encode()).hexdigest()


def _rounded(value: Any) -> Any:
    if isinstance(value, float):
        return round(value, 9)
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_rounded(v) for v in value]
    return value


def episode_rng(task_id: str, setting: str, seed: int, redraw: int = 0) -> np.random.Generator:
    """The one random stream of an episode: PCG64 seeded from a hash, identical on every platform. `redraw` k > 0
    gives the k-th replacement stream, for a layout the compiler rejected because it did not settle."""
    redrawn = f"|redraw {redraw}" if redraw else ""
    digest = hashlib.sha256(f"robodojo-scene|{task_id}|{setting}|{seed}{redrawn}".encode()).digest()
    return np.random.Generator(np.random.PCG64(int.from_bytes(digest[:16], "little")))


def setting_config(task: dict, setting: str) -> dict:
    """The task's randomization for a setting, over the setting's defaults."""
    if setting not in SETTINGS:
        raise ValueError(f"unknown setting '{setting}'; one of {', '.join(SETTINGS)}")
    defaults = RANDOM_DEFAULTS if setting == "random" else STANDARD_DEFAULTS
    return {**defaults, **task.get("settings", {}).get(setting, {})}


class _Sampler:
    def __init__(self, library: SpecLibrary, task: Spec, setting: str, seed: int, redraw: int):
        self.library, self.task, self.setting, self.seed = library, task, setting, seed
        self.cfg = setting_config(task.data, setting)
        self.rng = episode_rng(task.id, setting, seed, redraw)
        self.scene = task.data["scene"]
        self.fixtures: dict[str, PlacedObject] = {}  # filled as fixtures are placed, for regions on them
        self.colors_taken: dict[tuple[str, ...], set[str]] = {}  # objects sharing a colour list differ
        self.assets_taken: dict[tuple[str, ...], set[str]] = {}  # ... and so do objects sharing a query
        self.made: dict[str, PlacedObject] = {}  # the objects made so far this draw (for `like`)
        # Per object, the point of it that goes on its footprint centre at support height, from its frame origin
        # in its rest pose before yaw (`rest_pose.rested_box`); zero for an upright object.
        self.anchors: dict[str, np.ndarray] = {}

    def choose(self, candidates: list[Spec], vary: bool) -> Spec:
        """The first candidate by id, or with `vary` a random one, preferring candidates of this list that no
        earlier object took (five objects drawn from one query are five different things where possible)."""
        ordered = sorted(candidates, key=lambda s: s.id)
        if not vary or len(ordered) == 1:
            return ordered[0]
        used = self.assets_taken.setdefault(tuple(s.id for s in ordered), set())
        fresh = [s for s in ordered if s.id not in used] or ordered
        pick = fresh[int(self.rng.integers(len(fresh)))]
        used.add(pick.id)
        return pick

    def preset(self, key: str) -> str:
        if self.setting == "standard" and key not in self.task.data.get("settings", {}).get("standard", {}):
            return STANDARD_LOOK[key]
        ref = self.cfg.get(key, STANDARD_LOOK[key])
        return self.choose(self.library.resolve(self.task, "asset", ref), vary=True).id

    def object_entries(self) -> list[tuple[dict, str, bool]]:
        """(entry, instance name, is fixture) for every fixture and object, `count` expanded."""
        out = []
        for section, fixed in (("fixtures", True), ("objects", False)):
            for entry in self.scene.get(section, []):
                out.extend((entry, name, fixed) for name in instance_names(entry))
        return out

    def make_object(self, entry: dict, name: str, fixed: bool) -> PlacedObject:
        twin = self.made.get(entry.get("like", ""))  # a copy of an earlier object, as drawn for this episode
        if twin is not None:
            asset = self.library.resolve(self.task, "asset", twin.asset)[0]
        elif "draw_from" in entry:  # drawn in every setting: the episode's hidden fact (which number card)
            asset = self.choose([self.library.resolve(self.task, "asset", ref)[0] for ref in entry["draw_from"]],
                                vary=True)
        elif self.cfg["instances"] and "variants" in entry:
            asset = self.choose(self.library.resolve(self.task, "asset", entry["variants"]), vary=True)
        else:
            asset = self.choose(self.library.resolve(self.task, "asset", entry["asset"]), vary=self.cfg["instances"])
        lo, hi = asset.data.get("scale_range", [1.0, 1.0])
        want = entry.get("scale", [lo, hi])
        s_lo, s_hi = max(lo, want[0]), min(hi, want[1])
        if s_lo > s_hi:
            s_lo = s_hi = min(max(1.0, lo), hi)
        scale = float(self.rng.uniform(s_lo, s_hi)) if self.setting == "random" else (
            1.0 if s_lo <= 1.0 <= s_hi else (s_lo + s_hi) / 2)
        if twin is not None:
            scale = twin.scale
        color, rgba = entry.get("color"), None
        if "colors" in entry:
            taken = self.colors_taken.setdefault(tuple(entry["colors"]), set())
            free = [c for c in entry["colors"] if c not in taken] or list(entry["colors"])
            color = free[int(self.rng.integers(len(free)))]
            taken.add(color)
        choices = asset.data.get("colors")
        if color is not None:
            named = {c["name"]: c["rgba"] for c in choices or []}
            rgba = list(named.get(color, NAMED_COLORS.get(color, (0.5, 0.5, 0.5, 1.0))))
        elif choices and self.cfg["colors"]:
            pick = choices[int(self.rng.integers(len(choices)))]
            color, rgba = pick["name"], list(pick["rgba"])
        if twin is not None:
            color, rgba = twin.color, twin.rgba
        elif entry.get("color_of") in self.made:  # the colour an earlier object drew, on this object's asset
            color = self.made[entry["color_of"]].color
            named = {c["name"]: c["rgba"] for c in choices or []}
            rgba = list(named.get(color, NAMED_COLORS.get(color, (0.5, 0.5, 0.5, 1.0))))
        yaw_range = entry.get("yaw", [0.0, 0.0])
        yaw = float(self.rng.uniform(*yaw_range)) if yaw_range[0] != yaw_range[1] else float(yaw_range[0])
        b_lo, b_hi = asset_bounds(asset.data, asset.path.parent, scale) if asset.data["class"] in (
            "rigid", "articulated", "cloth") else (np.zeros(3), np.zeros(3))
        rest = entry.get("rest", "upright")
        anchor, b_lo, b_hi = rested_box(rest, b_lo, b_hi)
        b_lo, b_hi = b_lo - anchor, b_hi - anchor
        half = [float(max(-b_lo[i], b_hi[i])) for i in range(2)] + [float(b_hi[2] - b_lo[2]) / 2]
        self.anchors[name] = anchor
        attributes = {**asset.data.get("attributes", {}), **entry.get("attributes", {})}
        attributes.setdefault("name", asset.data["names"][0])
        if color:
            attributes.setdefault("color", color)
        x, y, z = entry.get("pos", (0.0, 0.0, 0.0))
        obj = PlacedObject(name=name, asset=asset.id, pos=[], yaw_deg=yaw, scale=scale, color=color, rgba=rgba,
                           fixed=fixed, group=entry.get("group"), attributes=attributes, half_extents=half, rest=rest)
        self.put(obj, float(x), float(y), float(z) + TABLE_TOP_Z)
        return obj

    def put(self, obj: PlacedObject, x: float, y: float, z: float) -> None:
        """Set the frame position that puts the object's footprint centre at (x, y) and its lowest point at
        height z: its rest pose's anchor, turned by its yaw, is taken off (nothing for an upright object)."""
        ax, ay = self.turned_anchor(obj)
        obj.pos = [x - ax, y - ay, z - float(self.anchors[obj.name][2])]

    def turned_anchor(self, obj: PlacedObject) -> tuple[float, float]:
        """The object's anchor in the ground plane, turned by its yaw."""
        anchor = self.anchors[obj.name]
        if not anchor.any():
            return 0.0, 0.0
        yaw = math.radians(obj.yaw_deg)
        return (math.cos(yaw) * float(anchor[0]) - math.sin(yaw) * float(anchor[1]),
                math.sin(yaw) * float(anchor[0]) + math.cos(yaw) * float(anchor[1]))

    def footprint(self, obj: PlacedObject) -> np.ndarray:
        """Where the centre of a placed object's footprint is (its frame position when it stands)."""
        ax, ay = self.turned_anchor(obj)
        return np.array([obj.pos[0] + ax, obj.pos[1] + ay]) if ax or ay else np.array(obj.pos[:2])

    def region_rect(self, region: str | None) -> tuple[np.ndarray, np.ndarray, float]:
        """(low corner, high corner, support height) of a region, or of the usable table top. A region `on` a
        fixture lies on the fixture's top, wherever the fixture was put."""
        if region is None:
            half = np.array(TABLE_HALF_SIZE) - TABLE_MARGIN
            return np.array([-half[0], ROBOT_STRIP_Y]), half, TABLE_TOP_Z
        spec = self.scene["regions"][region]
        c, s = np.array(spec["center"], float), np.array(spec["size"], float) / 2
        support = self.fixtures.get(spec.get("on", ""))
        z = TABLE_TOP_Z
        if support:  # its lowest point (frame height plus its anchor's) plus its height
            z = support.pos[2] + float(self.anchors[support.name][2]) + 2 * support.half_extents[2]
        return c - s, c + s, z

    def place(self, objects: list[PlacedObject], entries: list[dict], spacing: float) -> None:
        """Place every object without a fixed `pos` in its region; raise LayoutError if that is impossible.
        An object in a region `on` a fixture is not checked against that fixture: it rests on top of it."""
        for _ in range(LAYOUT_RESTARTS):
            self.fixtures = {o.name: o for o, e in zip(objects, entries) if o.fixed and "pos" in e}
            placed: list[tuple[str, np.ndarray, float]] = [
                (o.name, self.footprint(o), _radius(o)) for o, e in zip(objects, entries) if "pos" in e]
            failed: list[tuple[PlacedObject, str | None]] = []
            for obj, entry in zip(objects, entries):
                if "pos" in entry or "inside" in entry:
                    continue
                region = entry.get("region")
                support = self.scene["regions"][region].get("on") if region else None
                others = [(xy, r) for name, xy, r in placed if name != support]
                xy = self.sample_xy(region, _radius(obj), others, spacing)
                if xy is None:
                    failed.append((obj, region))
                    continue
                _, _, z = self.region_rect(region)
                self.put(obj, float(xy[0]), float(xy[1]), float(z))
                placed.append((obj.name, xy, _radius(obj)))
                if obj.fixed:
                    self.fixtures[obj.name] = obj
            if not failed:
                self.fill_containers(objects, entries)
                return
        regions = sorted({r or "table" for _, r in failed})
        names = ", ".join(o.name for o, _ in failed)
        raise LayoutError([self.task.problem(
            ("scene",), f"could not place {names} in region(s) {', '.join(regions)} without collisions after "
                        f"{ASSET_REDRAWS} draws x {LAYOUT_RESTARTS} layouts x {TRIES_PER_OBJECT} tries (setting {self.setting}, seed "
                        f"{self.seed}): enlarge the region(s) or make the objects fewer or smaller")])

    def fill_containers(self, objects: list[PlacedObject], entries: list[dict]) -> None:
        """Put the objects of every entry with `inside` into that container (granular contents: balls in a cup):
        in rings of as many as fit side by side within the container's `inside` placement box, layer upon layer
        from its bottom, each layer turned by half a place and a random jitter. Raise LayoutError when they do
        not fit below the box's top."""
        by_name = {o.name: o for o in objects}
        contents: dict[str, list[PlacedObject]] = {}
        for obj, entry in zip(objects, entries):
            if "inside" in entry:
                contents.setdefault(entry["inside"], []).append(obj)
        for container, objs in contents.items():
            centre, half = self.inside_box(by_name[container])
            r = max(max(o.half_extents[0], o.half_extents[1], o.half_extents[2]) for o in objs)
            place = 2.0 * r + CONTENT_GAP
            ring = max(0.0, float(min(half[0], half[1])) - r - CONTENT_GAP / 2)
            per_layer = 1 if 2.0 * ring < place else int(math.pi / math.asin(min(1.0, place / (2.0 * ring))))
            layers = -(-len(objs) // per_layer)
            if centre[2] - half[2] + CONTENT_GAP + (layers - 1) * place + 2.0 * r > centre[2] + half[2] + 1e-9:
                raise LayoutError([self.task.problem(("scene",), (
                    f"{len(objs)} objects ({objs[0].name}, ...) do not fit inside {container}: {per_layer} a layer, "
                    f"{layers} layers of {place * 100:.1f} cm above its bottom pass the top of its `inside` box"))])
            for i, obj in enumerate(objs):
                layer, k = divmod(i, per_layer)
                turn = 2.0 * math.pi * k / per_layer + (layer * math.pi / per_layer if per_layer > 1 else 0.0)
                turn += float(self.rng.uniform(-CONTENT_JITTER, CONTENT_JITTER))
                rho = ring if per_layer > 1 else 0.0
                z = centre[2] - half[2] + CONTENT_GAP + layer * place + r - obj.half_extents[2]
                x, y = centre[0] + rho * math.cos(turn), centre[1] + rho * math.sin(turn)
                self.put(obj, float(x), float(y), float(z))

    def inside_box(self, container: PlacedObject) -> tuple[np.ndarray, np.ndarray]:
        """World centre and half extents of a placed container's `inside` placement box (scaled, turned by its
        yaw: only the centre turns; the half extents are used for the inscribed circle)."""
        asset = self.library.resolve(self.task, "asset", container.asset)[0]
        box = next((a for a in asset.data.get("annotations", []) if a["name"] == "inside" and "size" in a), None)
        if box is None:
            raise LayoutError([self.task.problem(("scene",), f"objects are put inside {container.name}, whose asset "
                                                             f"{asset.id} has no `inside` placement box")])
        yaw = math.radians(container.yaw_deg)
        x, y, z = (container.scale * float(v) for v in box["pos"])
        centre = np.array([container.pos[0] + math.cos(yaw) * x - math.sin(yaw) * y,
                           container.pos[1] + math.sin(yaw) * x + math.cos(yaw) * y, container.pos[2] + z])
        return centre, container.scale * np.asarray(box["size"], float)

    def sample_xy(self, region: str | None, radius: float, placed: list[tuple[np.ndarray, float]],
                  spacing: float) -> np.ndarray | None:
        lo, hi, _ = self.region_rect(region)
        lo_in, hi_in = lo + radius, hi - radius
        too_big = lo_in > hi_in  # along an axis where the object is wider than the region, centre it there
        lo_in = np.where(too_big, (lo + hi) / 2, lo_in)
        hi_in = np.where(too_big, (lo + hi) / 2, hi_in)
        for _ in range(TRIES_PER_OBJECT):
            xy = self.rng.uniform(lo_in, hi_in)
            if all(np.linalg.norm(xy - p) >= radius + r + spacing for p, r in placed):
                return xy
        return None

    def clutter(self, objects: list[PlacedObject], spacing: float) -> int:
        """Add the sampled number of clutter objects where they fit (best effort: clutter that does not fit is
        left out, deterministically). Returns the number requested."""
        low, high = self.cfg["clutter"]
        count = int(self.rng.integers(low, high + 1)) if high > 0 else 0
        if count == 0:
            return 0
        pool = sorted(self.library.resolve(self.task, "asset", {"set": "clutter"}), key=lambda s: s.id)
        picks = self.rng.permutation(len(pool))[:count] if count <= len(pool) else self.rng.integers(len(pool), size=count)
        placed = [(self.footprint(o), _radius(o)) for o in objects]
        region = self.scene.get("clutter_region")
        for i, k in enumerate(picks):
            asset = pool[int(k)]
            obj = self.make_object({"asset": asset.id, "yaw": [-180.0, 180.0]}, f"clutter_{i}", fixed=False)
            obj.clutter = True
            xy = self.sample_xy(region, _radius(obj), placed, spacing)
            if xy is None:
                continue
            self.put(obj, float(xy[0]), float(xy[1]), TABLE_TOP_Z)
            placed.append((xy, _radius(obj)))
            objects.append(obj)
        return count

    def instruction(self, objects: list[PlacedObject]) -> tuple[str, dict[str, str]]:
        by_name = {o.name: o for o in objects}
        slots: dict[str, str] = {}
        for slot, spec in self.task.data.get("slots", {}).items():
            if "object" in spec:
                attribute = spec.get("attribute", "name")
                slots[slot] = str(by_name[spec["object"]].attributes.get(attribute, ""))
            else:
                slots[slot] = spec["choices"][int(self.rng.integers(len(spec["choices"])))]
        templates = [self.task.data["instruction"]] + list(self.task.data.get("paraphrases", []))
        template = templates[int(self.rng.integers(len(templates)))] if self.setting == "random" else templates[0]
        return template.format(**slots), slots


def _radius(obj: PlacedObject) -> float:
    """Footprint radius: the circle around the (rotated) footprint box, so any yaw fits."""
    return math.hypot(obj.half_extents[0], obj.half_extents[1])


def sample_scene(library: SpecLibrary, task: Spec, setting: str, seed: int, redraw: int = 0) -> SceneInstance:
    """Sample the scene of one episode. Raises LayoutError when the objects cannot be placed. `redraw` k > 0 draws
    the k-th replacement layout of the same episode (see `scene_settle`)."""
    sampler = _Sampler(library, task, setting, seed, redraw)
    lighting, background, texture = (sampler.preset(k) for k in ("lighting", "background", "table_texture"))
    expanded = sampler.object_entries()
    spacing = float(task.data["scene"].get("min_spacing", 0.02))
    for draw in range(ASSET_REDRAWS):
        # A layout can be infeasible only for the drawn instances (five large objects in a small region):
        # draw the instances again before giving up.
        sampler.assets_taken.clear()
        sampler.colors_taken.clear()
        sampler.made.clear()
        objects = []
        for entry, name, fixed in expanded:
            objects.append(sampler.make_object(entry, name, fixed))
            sampler.made[name] = objects[-1]
        try:
            sampler.place(objects, [entry for entry, _, _ in expanded], spacing)
            break
        except LayoutError:
            if draw == ASSET_REDRAWS - 1:
                raise
    requested = sampler.clutter(objects, spacing)
    instruction, slots = sampler.instruction(objects)
    return SceneInstance(task=task.id, setting=setting, seed=seed, instruction=instruction, slots=slots,
                         objects=objects, lighting=lighting, background=background, table_texture=texture,
                         clutter_requested=requested)
