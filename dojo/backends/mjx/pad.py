"""Padded scene models: plans of one task whose scenes differ in clutter, lights and textures made structurally equal.

MJX traces one program per model *structure*: every integer and `np.ndarray` field of `mjx.Model` (geom types,
contype, mesh vertices, texture pixels, name offsets, ...) is static, so two plans of one task in the `random`
setting (different clutter assets and counts, lighting presets, table textures) would land in different buckets and
each bucket would be a separate small batch. This module rewrites a group of plans' MJCF so that they share one
structure, leaving only *values* (poses, sizes, masses, colours, light parameters) to differ per environment:

- clutter: every plan gets the union of the group's clutter slots. A slot is keyed by the static signature of a
  clutter body (element tags, geom types, collision flags, mesh names; mesh names carry the scale, so the same key
  means the same vertices). A plan's clutter bodies fill the slots of their key; unused slots hold a copy of the
  slot's body *parked*: far above the scene, apart from each other, with gravity compensation so they stay put.
  `geom_type` and `contype` are static, so parking, not per-environment contact flags, is what disables a slot.
  Plans with different clutter counts therefore share a bucket.
- lights: padded to the group's largest count with inactive lights (`light_active` is a per-environment value).
- textures, materials, meshes: every plan's asset section gets the union of the group's 2-D textures, materials
  and meshes in one canonical order (`geom_matid` and `mat_texid` are values). A name that stands for different
  contents in different plans (the compiler names a mesh after its geom, so `clutter_0/body_0` is a bottle at one
  scale in one plan and a cup in the next) is first made unique per content (`_content_names`), so that the union
  holds every plan's own geometry and a slot's key tells different meshes apart. Skyboxes are left as they are:
  the renderer draws only one, so plans with different skyboxes stay in different buckets.
- the model, clutter, light and skybox names are canonical (name offsets are static fields), and so are clutter
  sites' sizes (`site_size` is static; clutter annotations are never read by a task's program).

Merged padding (`pad_group(..., every_object=True)`, what `make_buckets(merge=True)` asks for): the same slots, but
for every object of every plan in the group, not only clutter, so that plans of *different tasks* on one robot share
one structure. A block slot can be any task's block: its size, mass and colour are per-environment values. Per
key the union holds the most any plan needs (the max, not the sum), and a plan's objects fill the slots of their
key in the order of its spec's objects, so every plan of one task whose objects have the same keys maps them to
the same slots. Excludes inside one object (a button's cap and housing) are part of its key and are emitted for
every slot of that key, parked or not, so they do not split the group; other references to slot elements (contact
pairs, equalities, sensors, actuators) are renamed and, where they differ, split it.

The result is one MJCF per plan plus the name map back to the plan's own names; `bucket.py` compiles them and
groups by the exact structural signature, so anything this module does not equalise simply splits a bucket.
"""

from __future__ import annotations

import hashlib
import re
import xml.etree.ElementTree as ET
from collections import Counter
from dataclasses import dataclass, field
from typing import Sequence

from dojo.compiler.plan import Plan

PARK_ORIGIN = (50.0, 50.0, 20.0)
GRAVCOMP_IN_USE = 1e-9
"""Gravity compensation of slot bodies in use. MJX's `ngravcomp` (bodies with nonzero gravcomp) is static, so a used
slot keeps a negligible nonzero value (a 1e-9 fraction of its weight) rather than zero, and parked slots 1."""
PARK_SPACING = 3.0
"""Parked slots sit on a row far from the scene, PARK_SPACING metres apart (clutter is far smaller)."""
_STRUCTURAL_ATTRS = ("type", "contype", "conaffinity", "condim", "group", "priority", "mesh", "hfield", "joint",
                     "mocap", "childclass", "class")
_UNIONED_ASSETS = ("texture", "material", "mesh")

_SPLICE = "dojo-splice"
"""The tag of a placeholder `pad_group` serialises in place of a subtree every plan of its group shares (the asset
union, a parked slot), then replaces by that subtree's MJCF, serialised once (`_spliced`)."""
_SPLICED = re.compile(f'<{_SPLICE} at="([^"]+)" />')


def _spliced(xml: str, texts: dict[str, str]) -> str:
    """`xml` with each placeholder (`_SPLICE`) replaced by its text, in one pass."""
    return _SPLICED.sub(lambda found: texts[found.group(1)], xml)


@dataclass
class PaddedPlan:
    """One plan's padded MJCF and how its names map to the plan's own (padded name -> plan name)."""

    plan: Plan
    xml: str
    names: dict[str, str] = field(default_factory=dict)
    parked: list[str] = field(default_factory=list)
    """Top-level body names of the slots this plan leaves unused."""
    slot_keys: list[str] = field(default_factory=list)
    """The `slot_key` of every slot, in order: body `slot<j>` is a copy of key `slot_keys[j]` (what a merge costs
    is counted per key, see merge_groups.py)."""


_REFERENCES = {"body": "body", "body1": "body", "body2": "body", "joint": "joint", "joint1": "joint",
               "joint2": "joint", "site": "site", "site1": "site", "site2": "site", "geom": "geom", "geom1": "geom",
               "geom2": "geom"}
"""Attributes outside the worldbody that name an element, and the element's tag (renamed with the slot bodies)."""
_KEYED_ATTRS = frozenset(_STRUCTURAL_ATTRS) | set(_REFERENCES) | {"name"}
"""What `frame_key` keeps of an element: its structure, what it refers to, and its name (names are static too)."""


def _slot_bodies(plan: Plan, world: ET.Element, every_object: bool) -> list[ET.Element]:
    """The plan's slot bodies in the order of its objects: its clutter, or every object's top-level body."""
    by_name = {b.get("name"): b for b in world.findall("body")}
    if not every_object:
        names = [o["body"] for o in plan.objects.values() if o.get("clutter")]
        missing = [n for n in names if n not in by_name]
        if missing:
            raise ValueError(f"plan {plan.hash[:12]}: clutter bodies {missing} are not top-level bodies")
    else:  # an object whose body sits inside another's moves with that one's slot
        names = [o["body"] for o in plan.objects.values() if o.get("body") in by_name]
    return [by_name[n] for n in dict.fromkeys(names)]


def _canonical(body: ET.Element, slot: str) -> dict[tuple[str, str], str]:
    """Canonical names of a slot body's named elements, {(tag, old name): `slot` or `slot/<tag><k>`}."""
    mapping: dict[tuple[str, str], str] = {}
    counts: Counter[str] = Counter()
    for el in body.iter():
        old = el.get("name")
        if old is None:
            continue
        mapping[el.tag, old] = slot if el is body else f"{slot}/{el.tag}{counts[el.tag]}"
        counts[el.tag] += el is not body
    return mapping


def _inner_excludes(body: ET.Element, excludes: Sequence[ET.Element]) -> list[ET.Element]:
    """The contact excludes between two bodies of one slot body (an asset's own, e.g. a button's cap)."""
    names = {el.get("name") for el in body.iter("body")}
    return [e for e in excludes if e.get("body1") in names and e.get("body2") in names]


def _relative_excludes(body: ET.Element, excludes: Sequence[ET.Element]) -> list[tuple[str, str]]:
    """`_inner_excludes` by canonical names relative to the slot (`""` for its root, `/body<k>` below)."""
    canon = _canonical(body, "")
    return sorted((canon["body", e.get("body1")], canon["body", e.get("body2")])
                  for e in _inner_excludes(body, excludes))


def slot_key(body: ET.Element, excludes: Sequence[ET.Element] = ()) -> str:
    """Static signature of a slot body: what MJX treats as structure, with its own name prefix removed, and the
    excludes among its own bodies (an exclude changes MJX's static contact pairs)."""
    prefix = body.get("name", "") + "/"
    parts: list[str] = []
    for el in body.iter():
        attrs = {k: v for k, v in el.attrib.items() if k in _STRUCTURAL_ATTRS}
        for k in ("joint",):
            if k in attrs and attrs[k].startswith(prefix):
                attrs[k] = attrs[k][len(prefix):]
        parts.append(el.tag + repr(sorted(attrs.items())))
    inner = _relative_excludes(body, excludes)
    if inner:
        parts.append(f"exclude{inner!r}")
    return hashlib.sha256("|".join(parts).encode()).hexdigest()[:16]


def _rename(body: ET.Element, slot: str) -> dict[tuple[str, str], str]:
    """Give every named element of a slot body its canonical name (`_canonical`); return that map.

    Name offsets are static in MJX, so two assets with the same structure but differently named geoms would
    otherwise not share a bucket.
    """
    mapping = _canonical(body, slot)
    for el in body.iter():
        if el.get("name") is not None:
            el.set("name", mapping[el.tag, el.get("name")])
    return mapping


def _rename_references(root: ET.Element, renamed: dict[tuple[str, str], str]) -> None:
    """Rename references to renamed slot elements everywhere outside the worldbody (excludes, equalities, ...)."""
    for section in root:
        if section.tag in ("worldbody", "asset"):
            continue
        for el in section.iter():
            for attr, tag in _REFERENCES.items():
                new = renamed.get((tag, el.get(attr, "")))
                if new is not None:
                    el.set(attr, new)


def _canonical_sites(body: ET.Element, template: ET.Element) -> None:
    """Give a slot body's sites the template's sizes: `site_size` is static in MJX, and clutter sites (annotations
    for skills, never read by a task's program) are not worth a bucket each."""
    for site, ref in zip(body.iter("site"), template.iter("site")):
        if ref.get("size") is not None:
            site.set("size", ref.get("size"))


def _excludes(root: ET.Element) -> list[ET.Element]:
    contact = root.find("contact")
    return [] if contact is None else contact.findall("exclude")


def _park(body: ET.Element, index: int) -> None:
    x, y, z = PARK_ORIGIN
    body.set("pos", f"{x + PARK_SPACING * index:g} {y:g} {z:g}")
    body.set("quat", "1 0 0 0")
    for el in body.iter("body"):
        el.set("gravcomp", "1")


def _unioned(root: ET.Element) -> list[ET.Element]:
    """A plan's asset elements that the union replaces: 2-D textures, materials and meshes (skyboxes stay)."""
    asset = root.find("asset")  # the compiler writes one asset section
    return [el for el in (asset if asset is not None else ()) if el.tag in _UNIONED_ASSETS
            and el.get("type") != "skybox"]


def _copied(el: ET.Element) -> ET.Element:
    """A deep copy of an MJCF element, made element by element: `copy.deepcopy` copies each element's attributes
    through Python's `copy` module (0.44 against 0.24 ms a suite plan's tree), and padding every suite plan twice
    (`ParsedPlans`) took 1.7 s longer with it."""
    new = el.makeelement(el.tag, el.attrib)
    new.text, new.tail = el.text, el.tail
    new.extend([_copied(child) for child in el])
    return new


def _content(el: ET.Element) -> str:
    """What an asset element defines, without its name: its attributes and children, canonically.

    The layout around it is not content: `ET.tostring` writes an element's tail (the whitespace up to the next
    element), which differs with the element's place in its file, so two plans defining the same mesh, one of them
    last in its asset section, would count as different and be split into two structures."""
    body = _copied(el)
    body.attrib.pop("name", None)
    for part in body.iter():
        part.attrib = dict(sorted(part.attrib.items()))
        part.text = part.text.strip() if part.text else None
        part.tail = None
    return hashlib.sha256(ET.tostring(body, encoding="unicode").encode()).hexdigest()[:12]


class ParsedPlans:
    """Plans' MJCF parsed once, with the content (`_content`) of each of their unioned assets, for every padding of
    them in one `make_buckets` call; each padding takes a copy of its own to rewrite.

    Why: `make_buckets(merge=True)` pads a plan three to five times (with its task, as a unit, in its cluster, in
    pair checks: 4,967 paddings of the suite's 1,150 plans of seed 0), and each padding parsed the plan's MJCF
    again and serialised each of its meshes, textures and materials again to hash them (133,753 serialisations).
    Padding every suite plan twice (alone and with every object a slot) took 1.6 s longer that way on the 2-core CI
    machine (10.6 against 9.1 s, 2026-12-03). The suite's parsed trees hold about 190 MB: one is made per call."""

    def __init__(self) -> None:
        self._parsed: dict[str, tuple[ET.Element, list[str]]] = {}

    def _entry(self, plan: Plan) -> tuple[ET.Element, list[str]]:
        """The plan's parsed MJCF (never rewritten) and its unioned assets' contents, by its MJCF text."""
        entry = self._parsed.get(plan.model_xml)
        if entry is None:
            root = ET.fromstring(plan.model_xml)
            entry = self._parsed[plan.model_xml] = root, [_content(el) for el in _unioned(root)]
        return entry

    def root(self, plan: Plan) -> ET.Element:
        """A fresh copy of the plan's MJCF, the caller's to rewrite."""
        return _copied(self._entry(plan)[0])

    def contents(self, plan: Plan) -> list[str]:
        """`_content` of each of the plan's `_unioned` assets, in their order."""
        return self._entry(plan)[1]


def _content_names(roots: Sequence[ET.Element], contents: Sequence[Sequence[str]]) -> None:
    """Rename, in place, every unioned asset whose name the group's plans define with different contents to
    `<name>~<content hash>`, with the references to it in its own plan. The union keeps one definition per name, so
    without this a plan padded with others would silently take the first plan's mesh (or texture) of that name.
    Names defined alike everywhere are left as they are. `contents`: each root's `ParsedPlans.contents`."""
    found: dict[tuple[str, str], set[str]] = {}
    for root, hashes in zip(roots, contents, strict=True):
        for el, content in zip(_unioned(root), hashes, strict=True):
            found.setdefault((el.tag, el.get("name", "")), set()).add(content)
    clashing = {key for key, seen in found.items() if len(seen) > 1}
    if not clashing:
        return
    for root, hashes in zip(roots, contents):
        renamed: dict[tuple[str, str], str] = {}
        for el, content in zip(_unioned(root), hashes):
            key = (el.tag, el.get("name", ""))
            if key in clashing:
                renamed[key] = f"{key[1]}~{content}"
                el.set("name", renamed[key])
        for el in root.iter():  # a reference is an attribute named after the asset's tag (geom mesh=, material=)
            for tag in _UNIONED_ASSETS:
                new = renamed.get((tag, el.get(tag, "")))
                if new is not None:
                    el.set(tag, new)


def _asset_union(roots: Sequence[ET.Element]) -> list[ET.Element]:
    """The group's 2-D textures, materials and meshes, one per name, in a canonical order: the roots' own
    elements, which `pad_group` serialises before it rewrites any root."""
    seen: dict[tuple[str, str], ET.Element] = {}
    for root in roots:
        for el in _unioned(root):
            seen.setdefault((el.tag, el.get("name", "")), el)
    order = {tag: i for i, tag in enumerate(_UNIONED_ASSETS)}
    return [seen[k] for k in sorted(seen, key=lambda k: (order[k[0]], k[1]))]


def slotted_bodies(plans: Sequence[Plan], parsed: ParsedPlans | None = None,
                   ) -> list[tuple[ET.Element, list[tuple[str, ET.Element]]]]:
    """Each plan's MJCF with its clutter bodies taken out, and those bodies with their slot keys in order, as
    `pad_group` would see them when padding `plans` together (asset names made unique per content first): what
    padding them costs, and whether they could share a structure, can be told from these without compiling
    anything (merge_groups.py). `parsed`: the plans already parsed (`ParsedPlans`), else they are parsed here."""
    parsed = ParsedPlans() if parsed is None else parsed
    roots = [parsed.root(p) for p in plans]
    _content_names(roots, [parsed.contents(p) for p in plans])
    out = []
    for plan, root in zip(plans, roots):
        world = root.find("worldbody")
        bodies, excludes = _slot_bodies(plan, world, every_object=False), _excludes(root)
        keys = [slot_key(b, excludes) for b in bodies]
        for body in bodies:
            world.remove(body)
        out.append((root, list(zip(keys, bodies))))
    return out


def frame_key(root: ET.Element) -> str:
    """What padding cannot equalise in a plan whose slot bodies are taken out (`slotted_bodies`): every element
    outside the asset section (lights apart: padding evens their count) by its tag, name, structural attributes and
    references, with its values (poses, sizes, gains, colours) left out. Plans with different frame keys compile to
    different structures however they are padded (a geom on another mesh, another joint type); equal keys are a
    strong hint, not a promise (`bucket.py` still groups by the exact signature), and so is the skybox, left out
    here: its pixels are a per-environment value where the sizes agree."""
    parts: list[str] = []
    for section in root:
        if section.tag == "asset":
            continue
        for el in section.iter():
            if el.tag != "light":
                kept = {k: v for k, v in el.attrib.items() if k in _KEYED_ATTRS}
                parts.append(el.tag + repr(sorted(kept.items())))
    return hashlib.sha256("|".join(parts).encode()).hexdigest()[:16]


def pad_group(plans: Sequence[Plan], name: str, every_object: bool = False,
              parsed: ParsedPlans | None = None) -> list[PaddedPlan]:
    """Rewrite the MJCF of `plans` so that they share one structure where possible: normally one task's plans,
    with slots for their clutter; with `every_object`, plans of several tasks on one robot, with slots for every
    object (see the module docstring). `parsed`: the plans already parsed (`ParsedPlans`), else they are parsed
    here."""
    parsed = ParsedPlans() if parsed is None else parsed
    roots = [parsed.root(p) for p in plans]
    _content_names(roots, [parsed.contents(p) for p in plans])
    excludes = [_excludes(r) for r in roots]
    slotted = [_slot_bodies(p, r.find("worldbody"), every_object) for p, r in zip(plans, roots)]
    keys = [[slot_key(b, ex) for b in bodies] for bodies, ex in zip(slotted, excludes)]
    slots: list[tuple[str, ET.Element]] = []  # (key, template body) in canonical order
    need: Counter[str] = Counter()
    templates: dict[str, ET.Element] = {}
    inner: dict[str, list[tuple[str, str]]] = {}  # key -> its excludes, relative to the slot
    # Plans by `Plan.sort_key`, not in the given order: a key's template (its first body) gives its parked copies
    # and its sites' sizes (static), so the same plans in another order, or compiled by another install, must pick
    # the same one.
    for k in sorted(range(len(plans)), key=lambda k: plans[k].sort_key):
        bodies, ks, ex = slotted[k], keys[k], excludes[k]
        for key, count in Counter(ks).items():
            need[key] = max(need[key], count)
        for body, key in zip(bodies, ks):
            if key not in templates:  # the first body of a key is its template (its excludes computed once)
                templates[key] = body
                inner[key] = _relative_excludes(body, ex)
    for key in sorted(need):
        slots += [(key, templates[key])] * need[key]
    assets = _asset_union(roots)
    n_lights = max(len(r.find("worldbody").findall("light")) for r in roots)
    # What every plan shares is serialised once: ElementTree writes MJCF in Python at some 40 ns a character, and
    # in a merged padding of the random setting a plan's MJCF (1 MB) is mostly parked slots and the asset union,
    # 37 of its 46 ms (2-core CI machine, 2026-12-03); padding the protocol's 850 mjx plans for a merge at growth
    # 1.0 (3,006 paddings) took 8.8-9.9 s instead of 11.9-12.0, compiles on two threads beside it bounding the whole.
    # A subtree writes the same text alone as in its tree (no namespaces in MJCF), its tail included. Every plan
    # now parks a slot with the same text; copied plan by plan, a parked body followed its template, which the
    # template's own plan rewrites in place, so plans after that one had its attributes in another order (the
    # same model).
    shared = {"assets": "".join(ET.tostring(el, encoding="unicode") for el in assets)}

    out: list[PaddedPlan] = []
    for plan, root, bodies, ks, ex in zip(plans, roots, slotted, keys, excludes):
        root.set("model", name)
        world = root.find("worldbody")
        for body in bodies:
            world.remove(body)
            for exclude in _inner_excludes(body, ex):
                root.find("contact").remove(exclude)
        free = {key: [b for b, k in zip(bodies, ks) if k == key] for key in need}
        padded = PaddedPlan(plan, "", slot_keys=[key for key, _ in slots])
        renamed: dict[tuple[str, str], str] = {}
        for j, (key, template) in enumerate(slots):
            slot = f"slot{j}"
            if free[key]:
                body = free[key].pop(0)
                _canonical_sites(body, template)
                renamed.update(_rename(body, slot))
                for el in body.iter("body"):
                    el.set("gravcomp", repr(float(el.get("gravcomp", 0.0)) or GRAVCOMP_IN_USE))
            else:
                if slot not in shared:
                    parked = _copied(template)
                    _rename(parked, slot)
                    _park(parked, j)
                    shared[slot] = ET.tostring(parked, encoding="unicode")
                body = ET.Element(_SPLICE, {"at": slot})
                padded.parked.append(slot)
            world.append(body)
            if inner[key]:
                contact = root.find("contact")
                if contact is None:
                    contact = ET.SubElement(root, "contact")
                contact.extend(ET.Element("exclude", {"body1": slot + a, "body2": slot + b}) for a, b in inner[key])
        _rename_references(root, renamed)
        padded.names.update({new: old for (_, old), new in renamed.items()})
        lights = world.findall("light")
        for k, light in enumerate(lights):
            light.set("name", f"light{k}")
        at = list(world).index(lights[-1]) + 1 if lights else 0
        for k in range(len(lights), n_lights):
            world.insert(at, ET.Element("light", {"name": f"light{k}", "active": "false"}))
            at += 1
        asset = root.find("asset")
        if asset is None:
            asset = ET.SubElement(root, "asset")
        for el in _unioned(root):
            asset.remove(el)
        for el in asset.iter("texture"):
            if el.get("type") == "skybox":
                el.set("name", "skybox")
        asset.append(ET.Element(_SPLICE, {"at": "assets"}))
        padded.xml = _spliced(ET.tostring(root, encoding="unicode"), shared)
        out.append(padded)
    return out
