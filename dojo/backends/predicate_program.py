"""Compile a plan's success and score program into a static predicate tree, and evaluate it every control step.

`compile_program(plan, model)` resolves every name of `plan.program` against the plan and the compiled model
and returns a `CompiledProgram`:
- `layout` (`ProgramLayout`): the predicate tree with slot numbers instead of names, the stage names and
  weights. Hashable, and equal for all plans of one task with the same object counts: the MJX backend closes
  over it under jit and batches the environments that share it.
- `index` (`StateIndex`): where the frames, joints and contact atoms live in this model (`gather_state`).
- `params`: per-plan numbers as NumPy arrays without a batch axis (box centres and half extents of frames,
  constant frame positions, initial box centres for `lifted`, button rest and far positions). Stack them over
  environments to get the batched `params` that `program_step` reads.

`program_step(xp, layout, state, params, memory, step)` is pure: it returns the new memory (press counts,
first times for `ordered`, the step each stage was first reached) and a `ProgramOutput`. `init_memory` makes
the memory of a fresh episode. Evaluation semantics (task schema + DESIGN section 4):
- stages are latched: once reached they stay reached, and the first control step is kept (-1 = never);
- `stage_order: sequential`: a stage counts only when every earlier stage is reached (it may be in the same
  step);
- success = the success predicate holds now AND every stage is reached; score = 100 x weighted fraction of
  stages reached (100 x success when a task has no stages);
- `ordered([p, q, ...])` keeps the first step each child was true and holds once all were, in non-decreasing
  first steps (children first true in the same step count as in order); `pressed` counts up -> down
  transitions of the button from the episode's start; both are memory, so they survive the condition passing.
- `forall`/`exists` expand over the group's objects at compile time (`forall` of an empty group holds,
  `exists` does not); `stacked([a, b, c])` is `on(b, a) and on(c, b)`.

How a batched backend uses it (the CPU backend does the same with `np`, grouping slots by layout):

    programs = [compile_program(plan, model) for plan, model in bucket]    # once per plan, NumPy
    layout, index = programs[0].layout, programs[0].index                  # equal across a bucket: check it
    params = stack_params([p.params for p in programs])                    # [N, ...], device arrays if wished
    memory = init_memory(jnp, layout, N)                                   # and on reset: fresh rows
    def tick(d, memory, step):                                             # jit with layout/index closed over
        state = batched_state(jnp, index, params["const_pos"], d)          # d: mjx.Data stacked over N
        return program_step(jnp, layout, state, params, memory, step)      # -> memory, ProgramOutput

`step` is the control step just completed (1 after the first action); environments whose episode ended keep
their last output, and a reset replaces their memory rows with `init_memory` rows.
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from dojo.language import predicates as words
from dojo.language.predicates.connectives import AllOf

from dojo.backends import predicates as P
from dojo.backends.predicate_state import BODY, CONST, SITE, StateIndex, mujoco_state
from dojo.backends.program_json import program_from_json
from dojo.backends.program_types import CompiledProgram, Node, Press, ProgramError, ProgramLayout, ProgramOutput

Array = Any
ROBOT_ATOMS = ("left_arm", "right_arm")
"""Contact atoms for the robot: every geom of one arm (base to fingers). `robot` names both."""
TABLE = "table"


class _Compiler:
    """Allocates frame, joint, atom, press and order slots while walking the program."""

    def __init__(self, plan: Any, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        self.plan, self.model, self.data = plan, model, data
        self.frames: dict[str, int] = {}
        self.frame_kind: list[int] = []
        self.frame_id: list[int] = []
        self.frame_c: list[np.ndarray] = []
        self.frame_h: list[np.ndarray] = []
        self.const_pos: list[np.ndarray] = []
        self.joints: dict[str, int] = {}
        self.qpos_adr: list[int] = []
        self.speeds: dict[str, int] = {}
        self.dof_adr: list[int] = []
        self.atoms: dict[str, int] = {}
        self.atom_bodies: list[set[int]] = []
        self.presses: list[Press] = []
        self.press_slots: dict[str, int] = {}
        self.press_rest: list[float] = []
        self.press_far: list[float] = []
        self.n_order = 0
        self.start_poses = False

    # ---- names ----

    def _bodies_of(self, name: str) -> set[int]:
        """Body ids of an object (root and links), the table, or an arm."""
        m = self.model
        if name in self.plan.objects:
            return {m.body(b).id for b in self.plan.objects[name]["bodies"]}
        if name == TABLE:
            return {i for i in range(m.nbody) if m.body_rootid[i] == m.body(TABLE).id}
        if name in ROBOT_ATOMS:
            base = m.body(f"{name.removesuffix('_arm')}_base").id
            return {i for i in range(m.nbody) if m.body_rootid[i] == base}
        raise ProgramError(f"{name!r} is not an object of task {self.plan.task!r} (objects: "
                           f"{', '.join(sorted(self.plan.objects))}; also 'table', 'left_arm', 'right_arm', 'robot')")

    def _bbox(self, bodies: set[int], root: int) -> tuple[np.ndarray, np.ndarray]:
        """Centre and half extents, in the root body's frame, of the collision geoms of `bodies` at the plan's
        initial state (all geoms when none collides)."""
        m, d = self.model, self.data
        geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] in bodies]
        colliding = [g for g in geoms if m.geom_contype[g] or m.geom_conaffinity[g]]
        geoms = colliding or geoms
        if not geoms:
            return np.zeros(3), np.zeros(3)
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
        rot = d.xmat[root].reshape(3, 3)
        points = []
        for g in geoms:
            centre, half = m.geom_aabb[g, :3], m.geom_aabb[g, 3:]
            corners = centre + signs * half
            world = d.geom_xpos[g] + corners @ d.geom_xmat[g].reshape(3, 3).T
            points.append((world - d.xpos[root]) @ rot)
        pts = np.concatenate(points)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        return (lo + hi) / 2, (hi - lo) / 2

    def _add_frame(self, key: str, kind: int, ident: int, c: np.ndarray, h: np.ndarray,
                   const: np.ndarray | None = None) -> int:
        if key not in self.frames:
            self.frames[key] = len(self.frame_kind)
            self.frame_kind.append(kind)
            self.frame_id.append(ident)
            self.frame_c.append(np.asarray(c, float))
            self.frame_h.append(np.asarray(h, float))
            self.const_pos.append(np.zeros(3) if const is None else np.asarray(const, float))
        return self.frames[key]

    def _surface_z(self, fixture: str | None) -> float:
        """World height of the top of the table, or of a fixture's bounding box, at the initial state."""
        name = fixture or TABLE
        root = self.model.body(self.plan.objects[name]["body"] if name in self.plan.objects else TABLE).id
        c, h = self._bbox(self._bodies_of(name), root)
        rot = self.data.xmat[root].reshape(3, 3)
        return float(self.data.xpos[root][2] + (rot @ c)[2] + np.abs(rot)[2] @ h)

    def is_region(self, ref: str) -> bool:
        return ref in self.plan.regions and ref not in self.plan.objects

    def _sites_of(self, obj: str) -> dict[str, str]:
        """Annotation name -> site name of an object, or of the table (its `table/<name>` sites)."""
        if obj == TABLE and obj not in self.plan.objects:
            return {n.split("/", 1)[1]: n for n in _site_names(self.model) if n.startswith(f"{TABLE}/")}
        return self.plan.objects.get(obj, {}).get("sites", {})

    def frame(self, ref: str) -> int:
        """Frame slot of an objref: object, `object/annotation`, region or `table`."""
        if ref in self.frames:
            return self.frames[ref]
        m = self.model
        if "/" in ref:
            obj, ann = ref.split("/", 1)
            sites = self._sites_of(obj)
            if ann not in sites:
                raise ProgramError(f"{ref!r}: {obj!r} has no annotation {ann!r} "
                                   f"(annotations: {', '.join(sorted(sites)) or 'none'})")
            site = m.site(sites[ann])
            half = site.size.copy() if site.type[0] == mujoco.mjtGeom.mjGEOM_BOX else np.zeros(3)
            return self._add_frame(ref, SITE, site.id, np.zeros(3), half)
        if self.is_region(ref):
            region = self.plan.regions[ref]
            centre = [*region["center"], self._surface_z(region.get("on"))]
            half = [region["size"][0] / 2, region["size"][1] / 2, 0.0]
            return self._add_frame(ref, CONST, -1, np.zeros(3), half, np.asarray(centre))
        bodies = self._bodies_of(ref)
        root = m.body(self.plan.objects[ref]["body"] if ref in self.plan.objects else TABLE).id
        c, h = self._bbox(bodies, root)
        return self._add_frame(ref, BODY, root, c, h)

    def annotated_frame(self, ref: str, annotation: str) -> int:
        """The frame of `ref/annotation` when `ref` has that annotation as a box (a placement box such as a
        plate's `top` or a basket's `inside`), else the frame of `ref` itself."""
        site = self._sites_of(ref).get(annotation) if "/" not in ref else None
        if site is not None and self.model.site(site).type[0] == mujoco.mjtGeom.mjGEOM_BOX:
            return self.frame(f"{ref}/{annotation}")
        return self.frame(ref)

    def atoms_of(self, ref: str) -> tuple[int, ...]:
        """Contact atoms of an objref (`robot` = both arms; an annotation stands for its object)."""
        name = ref.split("/", 1)[0]
        names = ROBOT_ATOMS if name == "robot" else (name,)
        out = []
        for n in names:
            if n not in self.atoms:
                bodies = self._bodies_of(n)
                self.atoms[n] = len(self.atom_bodies)
                self.atom_bodies.append(bodies)
            out.append(self.atoms[n])
        return tuple(out)

    def joint(self, ref: str) -> int:
        if "/" not in ref:
            raise ProgramError(f"{ref!r}: joint predicates take object/joint")
        if ref not in self.joints:
            jid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, ref)
            if jid < 0:
                obj = ref.split("/", 1)[0]
                known = [j.split("/", 1)[1] for j in self.plan.objects.get(obj, {}).get("joints", [])]
                raise ProgramError(f"{ref!r}: no such joint (joints of {obj!r}: {', '.join(known) or 'none'})")
            self.joints[ref] = len(self.qpos_adr)
            self.qpos_adr.append(int(self.model.jnt_qposadr[jid]))
        return self.joints[ref]

    def joint_speed(self, ref: str) -> int:
        """Column of `state["qvel"]` holding the speed of joint `ref` (object/joint; one per joint)."""
        self.joint(ref)  # checks the name, listing the object's joints when it is wrong
        if ref not in self.speeds:
            self.speeds[ref] = len(self.dof_adr)
            self.dof_adr.append(int(self.model.joint(ref).dofadr[0]))
        return self.speeds[ref]

    def press(self, ref: str) -> int:
        """Press slot of a button (one per button, however many predicates count its presses).

        A button with a joint is down when the joint has travelled from its rest position (the initial one,
        clipped into the range) most of the way to the far end of its range; a button without joints is down
        while the robot touches it."""
        obj = ref.split("/", 1)[0]
        if obj not in self.plan.objects:
            raise ProgramError(f"pressed: {obj!r} is not an object")
        if obj in self.press_slots:
            return self.press_slots[obj]
        joints = self.plan.objects[obj]["joints"]
        if joints:
            slot = self.joint(joints[0])
            lo, hi = self.model.jnt_range[self.model.joint(joints[0]).id]
            rest = float(np.clip(self.data.qpos[self.qpos_adr[slot]], lo, hi))
            self.presses.append(Press(slot, None))
            self.press_rest.append(rest)
            self.press_far.append(float(lo if abs(lo - rest) >= abs(hi - rest) else hi))
        else:
            self.presses.append(Press(-1, (self.atoms_of(obj), self.atoms_of("robot"))))
            self.press_rest.append(0.0)
            self.press_far.append(1.0)
        self.press_slots[obj] = len(self.presses) - 1
        return self.press_slots[obj]

    def start_pose(self, ref: str) -> int:
        """Frame slot of an objref whose pose at the start of the episode a predicate compares with: the program's
        params then carry every frame's start rotation, `init_mat` (its start centre is `init_center`)."""
        self.start_poses = True
        return self.frame(ref)

    def group_members(self, group: str) -> list[str]:
        """The objects of a group, in a fixed order (quantifiers expand over them)."""
        return sorted(n for n, o in self.plan.objects.items() if o.get("group") == group)

    def order_slots(self, n: int) -> int:
        """Reserve n consecutive slots of `ordered` memory; returns the first."""
        first = self.n_order
        self.n_order += n
        return first

    # ---- predicates ----

    def node(self, pred: dict, bound: str | None = None) -> Node:
        """Compile one predicate through its word (`dojo.language.predicates`); `_` refers to `bound`."""
        (name, arg), = pred.items()

        def ref(r: str) -> str:
            if r == "_" or r.startswith("_/"):
                if bound is None:
                    raise ProgramError(f"{name}: '_' used outside forall/exists")
                return bound + r[1:]
            return r

        word = words.word(name)
        if word is None:
            raise ProgramError(f"unknown predicate {name!r}")
        return word.compile(self, arg, ref, bound)

    def geom_atom(self) -> tuple[int, ...]:
        n = len(self.atom_bodies)
        out = []
        for g in range(self.model.ngeom):
            body = int(self.model.geom_bodyid[g])
            out.append(next((k for k, bodies in enumerate(self.atom_bodies) if body in bodies), n))
        return tuple(out)


def _site_names(model: mujoco.MjModel) -> set[str]:
    return {model.site(i).name for i in range(model.nsite)}


def compile_program(plan: Any, model: mujoco.MjModel | None = None) -> CompiledProgram:
    """The plan's program: as resolved by `dojo compile` (`plan.compiled_program`), else resolved now."""
    if getattr(plan, "compiled_program", None):
        return program_from_json(plan.compiled_program)
    return resolve_program(plan, model)


def resolve_program(plan: Any, model: mujoco.MjModel | None = None) -> CompiledProgram:
    """Resolve `plan.program` against the plan's objects, regions and compiled model. Raises ProgramError with
    the offending name, and the spec path of the predicate (`success`, `stages.<i>.when`) as `.path`."""
    model = model or plan.model()
    data = plan.initial_data(model)
    comp = _Compiler(plan, model, data)
    program = plan.program
    conjuncts = program["success"].get("all") if isinstance(program["success"], dict) else None
    term_preds = conjuncts if isinstance(conjuncts, list) else [program["success"]]
    paths = [("success", "all", i) for i in range(len(term_preds))] if conjuncts else [("success",)]
    terms = tuple(_located(comp, pred, path) for pred, path in zip(term_preds, paths))
    success = AllOf(terms) if conjuncts else terms[0]  # the node `all` itself compiles to
    stages = tuple(_located(comp, s["when"], ("stages", i, "when")) for i, s in enumerate(program.get("stages", [])))
    triggers = tuple(_located(comp, e["when"], ("events", i, "when"))
                     for i, e in enumerate(program.get("events", [])) if "when" in e)
    layout = ProgramLayout(
        success=success, stages=stages, stage_names=tuple(s["name"] for s in program.get("stages", [])),
        weights=tuple(float(s.get("weight", 1.0)) for s in program.get("stages", [])),
        sequential=program.get("stage_order", "any") == "sequential", presses=tuple(comp.presses),
        n_order=comp.n_order, terms=terms, term_names=tuple(words.render(p) for p in term_preds), triggers=triggers,
    )
    index = StateIndex(tuple(comp.frame_kind), tuple(comp.frame_id), tuple(comp.qpos_adr), comp.geom_atom(),
                       len(comp.atom_bodies), tuple(comp.dof_adr))
    f = len(comp.frame_kind)
    c = np.asarray(comp.frame_c).reshape(f, 3)
    h = np.asarray(comp.frame_h).reshape(f, 3)
    const = np.asarray(comp.const_pos).reshape(f, 3)
    init = mujoco_state(index, const, data)
    init_center = P.box_center(np, init["pos"][0], init["mat"][0], c) if f else np.zeros((0, 3))
    params = {"frame_c": c, "frame_h": h, "const_pos": const, "init_center": init_center.reshape(f, 3),
              "press_rest": np.asarray(comp.press_rest, float), "press_far": np.asarray(comp.press_far, float)}
    if comp.start_poses:  # only then: plans of a task share one set of params keys, tasks without it keep theirs
        params["init_mat"] = init["mat"][0].reshape(f, 3, 3)
    return CompiledProgram(layout, index, params)


def _located(comp: _Compiler, predicate: dict, path: tuple) -> Node:
    try:
        return comp.node(predicate)
    except ProgramError as exc:
        exc.path = path
        raise


def init_memory(xp: Any, layout: ProgramLayout, n: int) -> dict[str, Array]:
    """Memory of n fresh episodes: no presses, no `ordered` child seen, no stage reached."""
    p, s = len(layout.presses), len(layout.stages)
    return {
        "press_count": xp.zeros((n, p), dtype=xp.int32),
        "press_down": xp.zeros((n, p), dtype=bool),
        "first": xp.full((n, layout.n_order), -1, dtype=xp.int32),
        "stage_step": xp.full((n, s), -1, dtype=xp.int32),
    }


class _Evaluator:
    """Evaluates nodes on one batch; records the `ordered` first-times it updates."""

    def __init__(self, xp: Any, state: dict, params: dict, memory: dict, press_count: Array, step: Any) -> None:
        self.xp, self.state, self.params, self.memory, self.step = xp, state, params, memory, step
        self.press_count = press_count
        self.n = state["qpos"].shape[0]
        self.first_updates: dict[int, Array] = {}
        self.values: dict[Node, Array] = {}

    def frame(self, k: int) -> tuple:
        s, p = self.state, self.params
        return s["pos"][:, k], s["mat"][:, k], p["frame_c"][:, k], p["frame_h"][:, k]

    def touching(self, atoms: tuple[tuple[int, ...], tuple[int, ...]] | None) -> Array:
        if atoms is None:
            return self.xp.ones((self.n,), dtype=bool)
        return P.touched(self.xp, self.state["contact"], atoms[0], atoms[1])

    def eval(self, node: Node) -> Array:
        """A node's value; equal nodes (a stage repeating the success predicate) are computed once."""
        if node not in self.values:
            self.values[node] = self._eval(node)
        return self.values[node]

    def _eval(self, node: Node) -> Array:
        evaluate = words.evaluator(type(node))
        if evaluate is None:
            raise TypeError(f"not a predicate node: {node!r}")
        return evaluate(self, node)

    def record_first(self, slot: int, first: Array) -> None:
        """The updated first-true step of `ordered` memory slot `slot` (kept by `program_step`)."""
        self.first_updates[slot] = first


def _columns(xp: Any, cols: list[Array], like: Array) -> Array:
    return xp.stack(cols, axis=-1) if cols else like


def program_step(xp: Any, layout: ProgramLayout, state: dict[str, Array], params: dict[str, Array],
                 memory: dict[str, Array], step: Any) -> tuple[dict[str, Array], ProgramOutput]:
    """Evaluate one control step of N environments that share `layout`.

    `state` from `gather_state`; `params` are the plans' params stacked over N (`stack_params`); `memory` from
    `init_memory` or the previous call; `step` the control step just completed (int or int[N], 1 = first).
    Pure and jit-able with `layout` static.
    """
    down_cols = []
    for k, press in enumerate(layout.presses):
        was = memory["press_down"][:, k]
        if press.joint >= 0:
            q = state["qpos"][:, press.joint]
            down_cols.append(P.press_down(xp, q, params["press_rest"][:, k], params["press_far"][:, k], was))
        else:
            down_cols.append(P.touched(xp, state["contact"], press.atoms[0], press.atoms[1]))
    down = _columns(xp, down_cols, memory["press_down"])
    count = P.count_presses(xp, memory["press_count"], memory["press_down"], down)

    ev = _Evaluator(xp, state, params, memory, count, step)
    success_now = ev.eval(layout.success)
    prev_steps = memory["stage_step"]
    steps, all_before = [], xp.ones((ev.n,), dtype=bool)
    for k, stage in enumerate(layout.stages):
        prev = prev_steps[:, k]
        now = ev.eval(stage)
        reached = (prev >= 0) | (now & all_before) if layout.sequential else (prev >= 0) | now
        steps.append(xp.where((prev < 0) & reached, step, prev))
        all_before = all_before & reached
    stage_step = _columns(xp, steps, prev_steps)
    reached = stage_step >= 0
    first = _columns(xp, [ev.first_updates[k] for k in range(layout.n_order)], memory["first"])
    success = success_now & xp.all(reached, axis=-1)
    if layout.stages:
        # An elementwise sum, not a matmul (GPUs may run float32 matmuls in TF32), clipped: rounding must not
        # put a full score a hair above 100.
        weights = np.asarray(layout.weights, dtype=np.float32)
        got = xp.sum(xp.where(reached, xp.asarray(weights), xp.float32(0.0)), axis=-1)
        score = xp.minimum(xp.float32(100.0) * got / xp.float32(weights.sum()), xp.float32(100.0))
    else:
        score = 100.0 * success.astype(xp.float32)
    memory = {"press_count": count, "press_down": down, "first": first, "stage_step": stage_step}
    terms = _columns(xp, [ev.eval(t) for t in layout.terms], xp.zeros((ev.n, 0), dtype=bool))
    triggers = _columns(xp, [ev.eval(t) for t in layout.triggers], xp.zeros((ev.n, 0), dtype=bool))
    return memory, ProgramOutput(success=success, score=score, stage_step=stage_step, terms=terms, triggers=triggers)


def stack_params(params: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Per-plan params (same layout) stacked over environments: the batched `params` of `program_step`."""
    return {k: np.stack([p[k] for p in params]) for k in params[0]}
