"""The batched engine: every bucket's environments advance one control step inside one jitted call.

Layout. A bucket of B environments holds its `mjx.Data` batched along axis 0 and, per environment, the index of
the bucket member (plan) it simulates. The member table (varying model fields and initial states, one row per
plan) lives on the device; each tick gathers the rows of the current members and vmaps `mjx.step` over the data
*and* those fields (`in_axes` 0 for the varying fields, None for the shared model). A tick applies resets, writes
the controls, runs the plan's physics sub-steps (`n_substeps` per 25 Hz control step; under Warp as one call, see
`substeps`), and recomputes kinematics so that positions match the new state. The buckets of a tick are traced
into one program, so the device runs different tasks' batches concurrently instead of one after another; up to
`PROGRAM_BUCKETS` of them, since one program over a whole suite's buckets compiles for too long and in too much
memory (`make_engine`, `EngineGroups`).

Continuous batching. Refilling an environment is "set its member index and its reset flag", both ordinary
inputs of fixed shape, so the program compiled for the first tick serves the whole run.

Stable types. MJX's `make_data` mixes weak and strong types and a few dtypes that `step` returns changed, and
its arrays are not committed to a device while a jitted call's outputs are; feeding a tick's output back would
then compile the tick a second time. `Engine` casts the initial state to the exact types one tick returns (read
with `jax.eval_shape`, no compilation) and commits it, so the state's types are a fixed point from the first
call on (`Engine.compilations()` stays 1). Split (`streams`), the data keeps `make_data`'s types, which are the
lanes' (checked against Warp's arrays), and only the extra state is cast, to the types the two halves return.

Compiled ahead. `make_engine` compiles the programs the first tick will run (`compile_ahead`), every group's on
threads side by side, from arguments of exactly the first tick's types, so that the tick finds them compiled.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import reduce
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from dojo.backends.mjx.bucket import Bucket, member_data
from dojo.backends.mjx.capture import run_settled, wait_for
from dojo.backends.mjx.sharding import Placement
from dojo.backends.mjx.substeps import substeps

log = logging.getLogger(__name__)
Tree = Any
# Per-world state a reset or a non-stepping environment restores; everything else is derived from it by a step.
STATE_FIELDS = ("qpos", "qvel", "ctrl", "act", "time", "qacc_warmstart")


REST_MARGIN = 2
"""Contacts and constraint rows allocated per world are at least this many times what the bucket's plans have at
rest (their initial states, `mj_forward` on the CPU): grasps, pushes and stacks add contacts to a resting layout."""
OVERFLOW_FLAGS = {1 << 0: "constraint rows (njmax)", 1 << 1: "constraint Jacobian non-zeros (njmax_nnz)",
                  1 << 2: "broadphase pairs (naconmax)", 1 << 3: "contacts (naconmax)",
                  1 << 4: "CCD contacts (naccdmax)", 1 << 5: "height-field contacts",
                  1 << 6: "contact-match sensor", 1 << 7: "awake dofs (nvmax)", 1 << 8: "EPA horizon",
                  1 << 11: "tactile sensor pairs"}
"""MuJoCo Warp's `OverflowType` bits (mujoco_warp 4.0 `types.OverflowType`) that mean a buffer was too small and
contacts or constraint rows were dropped. The solver's iteration-limit bits (1 << 9, 1 << 10) are left out: they
report convergence, not lost physics. Warp ORs these bits into `Data.overflow` per world and never clears them."""


class CapacityOverflow(RuntimeError):
    """A Warp buffer was too small: contacts or constraint rows were dropped, so the physics is not the plan's."""


def raise_overflow(found: dict[str, dict[str, int]], arrays: Sequence[BucketArrays]) -> None:
    """Raise `CapacityOverflow` naming each bucket of `found` ({bucket key: {what: worlds}}), its buffers and world
    counts, and what it had allocated; nothing when `found` is empty."""
    if found:
        capacity = {a.bucket.key: contact_capacity(a.bucket) for a in arrays if a.bucket.key in found}
        lines = [f"{key}: {', '.join(f'{what} in {n} world(s)' for what, n in flags.items())} (allocated "
                 f"{capacity[key][0]} contacts and {capacity[key][1]} constraint rows per world)"
                 for key, flags in found.items()]
        raise CapacityOverflow("MuJoCo Warp dropped contacts or constraints, so these results are not the "
                               "plans' physics: " + "; ".join(lines) + ". Raise REST_MARGIN in "
                               "dojo/backends/mjx/batch.py or report the scene.")


def contact_capacity(bucket: Bucket) -> tuple[int, int]:
    """(contacts, constraint rows) to allocate per world for the warp implementation, sized from the plans.

    Warp preallocates contact and constraint buffers; too few drops contacts (detected: `Engine.check_overflow`),
    too many costs memory. Grasps and stacked objects touch with a few points per colliding geom, so the contact
    budget scales with the colliding geoms; an elliptic cone contact takes up to 6 rows (condim 6), plus rows for
    limits and equalities. Both are raised to REST_MARGIN times the most any member has at rest. Geoms of parked
    slots (far from the scene and from each other) never touch: a geom counts for the member that uses it, and the
    budget is the most any member needs, which matters for buckets merged across tasks (most slots parked).
    """
    m = bucket.model
    colliding = max(_live_colliding(member.model, member.padded.parked) for member in bucket.members)
    rest_contacts, rest_rows = rest_constraints(bucket)
    contacts = max(64, 4 * colliding, REST_MARGIN * rest_contacts)
    return contacts, max(6 * contacts + 2 * m.njnt + 4 * m.neq, REST_MARGIN * rest_rows)


def _live_colliding(model: mujoco.MjModel, parked: Sequence[str]) -> int:
    """Colliding geoms of a padded model outside its parked slots (top-level bodies named in `parked`)."""
    parked_ids = [model.body(name).id for name in parked]
    live = ~np.isin(model.body_rootid[model.geom_bodyid], parked_ids)
    return int(np.sum(((model.geom_contype != 0) | (model.geom_conaffinity != 0)) & live))


def rest_constraints(bucket: Bucket) -> tuple[int, int]:
    """The most contacts and constraint rows any member of the bucket has in its initial state (CPU MuJoCo)."""
    counts = rest_counts(bucket)
    return max(c for c, _ in counts), max(r for _, r in counts)


def rest_counts(bucket: Bucket) -> list[tuple[int, int]]:
    """Each member's contacts and constraint rows in its initial state (`member_data`: 6 s for 6,144
    `insert_tubes` plans on the H200 host when each member allocated its own MjData)."""
    counts = []
    for member, data in member_data(bucket.members):
        data.qpos[:], data.qvel[:], data.ctrl[:] = member.qpos, member.qvel, member.ctrl
        mujoco.mj_forward(member.model, data)
        counts.append((int(data.ncon), int(data.nefc)))
    return counts


def decode_overflow(bits: Any) -> dict[str, int]:
    """{what overflowed: how many worlds} from per-world Warp overflow bitmasks (only buffer-size flags)."""
    bits = np.asarray(bits).reshape(-1).astype(np.int64)
    return {name: int(np.count_nonzero(bits & flag)) for flag, name in OVERFLOW_FLAGS.items()
            if np.any(bits & flag)}


@dataclass
class BucketArrays:
    """A bucket on the device: shared model, member table, `in_axes` for the gathered model."""

    bucket: Bucket
    size: int
    mx: Tree
    table: dict[str, jax.Array]
    in_axes: Tree


def _prepare(bucket: Bucket, size: int, impl: str, placement: Placement, graph_mode: object | None = None
             ) -> BucketArrays:
    """The bucket's model and member table, replicated on every device of `placement`; `graph_mode` (warp only,
    `cache.graph_mode`) how MJX captures its Warp calls, MJX's default when None.

    The table is cast by NumPy and put on the devices in one call: casting field by field with `jnp.asarray` ran an
    eager JAX program per field, some 12 s of the protocol's 141 buckets' engine build on an H200 (2026-12-03, stack
    samples)."""
    mx = mjx.put_model(bucket.model, impl=impl, graph_mode=graph_mode)
    table = {}
    for name, rows in bucket.table().items():
        if hasattr(mx, name):  # the implementation's layout: warp keeps e.g. geom_aabb as [ngeom, 2, 3], not [ngeom, 6]
            field = getattr(mx, name)
            table[name] = np.asarray(rows.reshape((len(rows),) + field.shape), dtype=field.dtype)
        else:
            table[name] = np.asarray(rows, dtype=np.float32)
    in_axes = jax.tree.map(lambda _: None, mx).tree_replace({name: 0 for name in bucket.varying})
    return BucketArrays(bucket, size, placement.put_replicated(mx), placement.put_replicated(table), in_axes)


def _initial_data(arr: BucketArrays, impl: str) -> Tree:
    """A batch of `size` environments, each at member 0's initial state (reset flags choose the real members), as
    NumPy arrays on the host: one environment's data made once and broadcast without copying.

    Why on the host: `Engine` takes its state to the host anyway (`_stable`), and vmapping `make_data` broadcast
    each of a data's some 185 leaves by an eager JAX call, each dispatched and looked up in JAX's caches on its own:
    56 s of a 238 s engine build for the protocol's 141 buckets on an H200 (2026-12-03, stack samples), 7.5 of
    12.1 s for 8 real buckets on the CI machine."""
    m = arr.bucket.model
    if impl == "warp":
        contacts, rows = contact_capacity(arr.bucket)
        one = mjx.make_data(m, impl="warp", naconmax=contacts * arr.size, njmax=rows)
    else:
        one = mjx.make_data(m, impl="jax")
    one = jax.device_get(one)
    one = one.replace(qpos=np.asarray(arr.bucket.members[0].qpos, one.qpos.dtype))  # row 0 of `table`
    # which leaves a batch holds per environment is MJX's to say (Warp's contact pool is one for all worlds)
    shapes = jax.eval_shape(jax.vmap(lambda q: one.replace(qpos=q)), np.broadcast_to(one.qpos, (arr.size, m.nq)))
    return jax.tree.map(lambda x, s: np.broadcast_to(x, s.shape), one, shapes)


def may_capture(impl: str, graph_mode: str, tick: int) -> bool:
    """Whether tick number `tick` (0 = the first) of an engine may capture CUDA graphs (`capture`): only under
    `warp`; in the staged modes only the first tick (one capture per call), in MJX's default mode (`warp`) every
    tick (it captures again for every new set of buffer addresses), with `none` never."""
    if impl != "warp" or graph_mode == "none":
        return False
    return tick == 0 or graph_mode == "warp"


def _select(mask: jax.Array, new: Tree, old: Tree) -> Tree:
    """Per-environment choice between two batched states, on the per-world state fields only."""
    def pick(name: str) -> jax.Array:
        a, b = getattr(new, name), getattr(old, name)
        return jnp.where(mask.reshape((-1,) + (1,) * (a.ndim - 1)), a, b)
    return new.replace(**{name: pick(name) for name in STATE_FIELDS})


class Hooks:
    """What a tick does besides physics; the defaults are physics only (the bench), the backend adds actions,
    predicates and observations. All methods are traced inside the tick, per bucket, batched over its envs.

    `init_extra` is the per-env state the hooks carry between ticks (reset rows are re-initialised from it);
    `act` may make the tick's inputs from that state instead of taking them from the host (a policy running in the
    tick; default: the inputs as given); `control` maps the inputs to actuator controls [B, nu] (default: the inputs
    are controls); `observe` runs after the physics, on up-to-date positions, and returns the new extra state and
    the outputs.
    """

    def refresh(self, m: Tree, d: Tree) -> Tree:
        """One environment's derived quantities brought up to date with its new state after the sub-steps, for
        `observe` (traced per environment under `vmap`). Kinematics only by default: all the benchmark reads.
        Under `Engine`'s `streams` the lanes refresh instead (`streams.refresh`: poses, tendons, contacts)."""
        return mjx.kinematics(m, d)

    def init_extra(self, arr: BucketArrays) -> Tree:
        return ()

    def act(self, arr: BucketArrays, extra: Tree, member: jax.Array, inputs: Tree, stepping: jax.Array
            ) -> tuple[Tree, Tree]:
        """(the inputs `control` gets, the new extra state), from the extra state as the resets left it."""
        return inputs, extra

    def control(self, arr: BucketArrays, m: Tree, data: Tree, inputs: Tree) -> tuple[jax.Array, Tree]:
        return inputs, ()

    def observe(self, arr: BucketArrays, m: Tree, data: Tree, extra: Tree, member: jax.Array, reset: jax.Array,
                stepping: jax.Array, aux: Tree, steps: jax.Array) -> tuple[Tree, Tree]:
        return extra, ()


def _gathered(arr: BucketArrays, mx: Tree, table: dict[str, jax.Array], member: jax.Array
              ) -> tuple[BucketArrays, Tree, dict[str, jax.Array]]:
    """The bucket at this device's batch size, the model each environment simulates (its member's rows of the
    varying fields in the shared model) and those rows."""
    rows = {name: table[name][member] for name in arr.bucket.varying}
    return dataclasses.replace(arr, size=member.shape[0]), mx.tree_replace(rows), rows


def _before_physics(arr: BucketArrays, hooks: Hooks, m: Tree, table: dict[str, jax.Array], data: Tree,
                    extra: Tree, member: jax.Array, reset: jax.Array, stepping: jax.Array, inputs: Tree
                    ) -> tuple[Tree, Tree, Tree, Tree]:
    """Resets, the hooks' actions and controls: (the data after the resets, the same with the stepping envs'
    controls written, the extra state, the controls' aux outputs)."""
    init = data.replace(qpos=table["qpos"][member].astype(data.qpos.dtype),
                        qvel=table["qvel"][member].astype(data.qvel.dtype),
                        ctrl=table["ctrl"][member].astype(data.ctrl.dtype),
                        geom_xpos=table["geom_xpos"][member].astype(data.geom_xpos.dtype),
                        geom_xmat=table["geom_xmat"][member].astype(data.geom_xmat.dtype),
                        act=jnp.zeros_like(data.act), time=jnp.zeros_like(data.time),
                        qacc_warmstart=jnp.zeros_like(data.qacc_warmstart))
    data = _select(reset, init, data)
    fresh = hooks.init_extra(arr)
    extra = jax.tree.map(lambda f, e: jnp.where(reset.reshape((-1,) + (1,) * (e.ndim - 1)), f, e), fresh, extra)
    inputs, extra = hooks.act(arr, extra, member, inputs, stepping)
    ctrl, aux = hooks.control(arr, m, data, inputs)
    driven = data.replace(ctrl=jnp.where(stepping[:, None], ctrl.astype(data.ctrl.dtype), data.ctrl))
    return data, driven, extra, aux


def _after_physics(arr: BucketArrays, hooks: Hooks, m: Tree, data: Tree, stepped: Tree, extra: Tree,
                   member: jax.Array, reset: jax.Array, stepping: jax.Array, aux: Tree, steps: jax.Array
                   ) -> tuple[Tree, Tree, Tree]:
    """The stepping envs' new state, brought up to date (`Hooks.refresh`) and observed: (data, extra, outputs)."""
    data = _select(stepping, stepped, data)
    data = jax.vmap(hooks.refresh, in_axes=(arr.in_axes, 0))(m, data)
    extra, outputs = hooks.observe(arr, m, data, extra, member, reset, stepping, aux, steps)
    return data, extra, outputs


def _bucket_tick(arr: BucketArrays, hooks: Hooks, mx: Tree, table: dict[str, jax.Array], data: Tree, extra: Tree,
                 member: jax.Array, reset: jax.Array, stepping: jax.Array, inputs: Tree, steps: jax.Array
                 ) -> tuple[Tree, Tree, Tree]:
    """One control step of one bucket (traced inside `Engine.tick`), on the rows of the batch this device holds."""
    arr, m, _ = _gathered(arr, mx, table, member)
    data, driven, extra, aux = _before_physics(arr, hooks, m, table, data, extra, member, reset, stepping, inputs)
    stepped = substeps(mx.impl.value, arr.bucket.n_substeps, arr.in_axes)(m, driven)
    return _after_physics(arr, hooks, m, data, stepped, extra, member, reset, stepping, aux, steps)


def _call(fn: Callable[..., Any], *args: Any) -> Any:
    """`fn(*args)`: how a tick calls its jitted parts when they capture no CUDA graph (`capture.run_settled` when
    they may)."""
    return fn(*args)


def _stable(tree: Tree, like: Tree, placement: Placement) -> Tree:
    """`tree` with the dtypes of `like`, no weak types, committed to the devices like a jitted call's outputs
    (split along the batch axis).

    A host round trip makes every leaf strongly typed; committing matters too: jit keys its cache on it, and
    uncommitted first inputs followed by committed outputs compiled the tick twice.
    """
    return jax.tree.map(lambda x, s: placement.put_batched(np.asarray(x).astype(s.dtype)), tree, like)


class _NotGiven:
    """A model leaf the halves of a split tick are not given (`Engine`'s `streams`): they read the varying model
    rows from the tables, because each array a jitted call takes costs host time on every call (136 model leaves a
    bucket). A hook that reads another model field there fails at trace time with the field's name, instead of
    reading a wrong value."""

    def __init__(self, name: str) -> None:
        self.name = name

    def __repr__(self) -> str:
        return (f"<{self.name}: not given to the halves of a split tick (backend.streams), which read only the "
                f"model's varying rows>")

    def __getattr__(self, attr: str) -> Any:
        raise AttributeError(f"{self!r} has no .{attr}")

    def __getitem__(self, index: Any) -> Any:
        raise TypeError(f"{self!r} cannot be indexed")


class Engine:
    """The device side of the mjx backend: buckets' batches, their member indices, and the one jitted tick.

    `tick(members, resets, stepping, inputs, steps)` takes, per bucket, int32 member indices [B], reset and
    stepping flags [B], the hooks' inputs (controls [B, nu] by default) and the control step each env completes
    (int32 [B], for predicates); it keeps the new state (`self.data`) and returns the hooks' outputs per bucket
    (device arrays; without `streams` nothing waits for the device). Envs with the reset flag start their member's
    episode; only envs with the stepping flag advance.

    `placement` (all local devices when None): every batch is split over its devices along the env axis
    (`sharding`), so each size must be a multiple of their count (`Placement.padded`). `graph_mode`: MJX's CUDA
    graph capture of Warp calls (`cache.graph_mode`; None is MJX's default). Ticks that may capture run settled
    (`capture.run_settled`): nothing is freed on the host until they finish.

    `streams` (warp, one device): the physics runs between two jitted halves of the tick, every bucket on its own
    CUDA stream (`streams.StreamPhysics`, which holds a second copy of each bucket's data); a tick then returns
    when its outputs are computed. Each lane ends its tick by refreshing, at the state every environment holds,
    the poses, tendons and contacts as MuJoCo Warp's forward computes them (`streams.refresh`), which takes the
    place of `Hooks.refresh` (the backend's is a whole forward, of which the observations read only those; the
    default's kinematics are part of it), and returns its whole data, the rest of it as the last sub-step left
    it. The halves take no model leaf, and each bucket's data as one array (`_split`).
    """

    _physics: Any = None
    """`streams.StreamPhysics` with `streams`; None: the physics runs inside the jitted tick."""
    split_ms: dict[str, list[float]] | None = None
    """With `streams`, set to {"first_half": [], "lanes": [], "second_half": []}: each tick appends the wall
    milliseconds of its parts, each waited for (`dojo bench sim` reports their medians)."""

    def __init__(self, buckets: Sequence[Bucket], sizes: Sequence[int], impl: str, hooks: Hooks | None = None,
                 example_inputs: Sequence[Tree] | None = None, placement: Placement | None = None,
                 graph_mode: object | None = None, streams: bool = False):
        self.impl = impl
        self.hooks = hooks or Hooks()
        self.placement = placement or Placement.over(None, impl)
        self.placement.check(sizes)
        self.arrays = [_prepare(b, n, impl, self.placement, graph_mode) for b, n in zip(buckets, sizes)]
        p = self.placement  # models and tables replicated, the other 7 arguments split along the env axis
        self._tick = jax.jit(p.per_device(self._flat(self._tick_all), 2, 7), donate_argnums=(2, 3),
                             in_shardings=p.in_shardings(2, 7), out_shardings=p.batched)
        if streams and (impl != "warp" or p.count != 1):
            raise ValueError("backend.streams runs MuJoCo Warp on one device: it needs impl=warp and devices=1")
        data = tuple(_initial_data(a, impl) for a in self.arrays)
        extra = tuple(self.hooks.init_extra(a) for a in self.arrays)
        inputs = tuple(example_inputs) if example_inputs is not None else tuple(
            jnp.zeros((a.size, a.bucket.model.nu), jnp.float32) for a in self.arrays)
        self._model_leaves, self._model_def = jax.tree.flatten(self._models())
        self._table_leaves, self._table_def = jax.tree.flatten(self._tables())
        if streams:  # the lanes' words hold the data as `make_data` typed it (`StreamEngine` checks Warp's types)
            leaves, self._data_def = jax.tree.flatten(jax.tree.map(np.asarray, data))
            self._extra_def = jax.tree.structure(extra)
        else:
            flags = self._flags()
            shapes = jax.eval_shape(self._tick_all, self._models(), self._tables(), data, extra, *flags[:3], inputs,
                                    flags[3])
            leaves, self._data_def = jax.tree.flatten(_stable(data, tuple(s[0] for s in shapes), p))
            self._extra_leaves, self._extra_def = jax.tree.flatten(_stable(extra, tuple(s[1] for s in shapes), p))
        self._data_empty = {k: x for k, x in enumerate(leaves) if x.size == 0}
        """The data's empty arrays by position (fields a scene lacks: tendons, sensors, flex): kept out of the
        tick's arguments and outputs, where each array costs a call its handling whatever its size (38 of a
        MuJoCo Warp data's 185 on the built-in tasks)."""
        self._data_leaves = [x for k, x in enumerate(leaves) if k not in self._data_empty]
        ahead: list[tuple[Callable[..., Any], tuple]]
        if streams:
            self._split(buckets, sizes, jax.tree_util.tree_flatten_with_path(data)[0])
            types, ahead = self._split_extra_types(extra, inputs)
            self._extra_leaves = jax.tree.leaves(_stable(extra, types, p))
            self._data_leaves = None  # unpacked from the words when `data` is read, as after every split tick
        else:
            ahead = [(self._tick, (self._model_leaves, self._table_leaves, self._data_leaves, self._extra_leaves,
                                   *flags[:3], inputs, flags[3]))]
        self._ahead = ahead
        """The programs the first tick runs, each with arguments of that tick's types (`compile_ahead`)."""
        self._data: tuple[Tree, ...] | None = None
        self._graphs = str(getattr(graph_mode, "name", "warp")).lower()  # None is MJX's default, `warp`
        self._ticks = 0

    def _split(self, buckets: Sequence[Bucket], sizes: Sequence[int], data_paths: Sequence[tuple[Any, Any]]
               ) -> None:
        """The split tick (`streams`): the lanes (`StreamPhysics`), told which data leaves the tick keeps, and the
        two jitted halves (`_split_flat`).

        Between ticks each bucket's data is a copy of its lane's outbox (`_words`: the leaves the lane returns as
        one flat array of words) and the leaves it does not return (`_split_leaves`: fields of other widths such
        as `eq_active`, and MJX's own token, which no tick changes), so that a half takes one array a bucket where
        it took some 150 data and 136 model leaves: each costs host time on every call. `Engine.data` unpacks the
        words when read (`_unpack`)."""
        from dojo.backends.mjx.streams import OUTBOX_ALIGN, StreamPhysics, pack_host_words, word_offsets, words_of

        names = [jax.tree_util.keystr(path[1:], simple=True, separator=".") for path, _ in data_paths]
        bucket_of = [path[0].idx for path, _ in data_paths]
        kept = [k for k in range(len(names)) if k not in self._data_empty]
        stable = dict(zip(kept, self._data_leaves))
        leaf_words = [{names[k]: (stable[k].size, stable[k].dtype) for k in kept
                       if bucket_of[k] == b and stable[k].dtype.itemsize == 4} for b in range(len(buckets))]
        self._physics = StreamPhysics(buckets, sizes, leaf_words)
        position = {(bucket_of[k], names[k]): k for k in kept}
        self._returned_at = [[position[b, name] for name in returned]
                             for b, returned in enumerate(self._physics.returned)]
        """Per bucket, the positions among the data's leaves of those its lane returns, in its outbox's order."""
        self._returned_like = [[jax.ShapeDtypeStruct(stable[k].shape, stable[k].dtype) for k in at]
                               for at in self._returned_at]
        self._returned_words = [{name: (start, like) for name, start, like in
                                 zip(names_b, word_offsets([words_of(x) for x in likes], OUTBOX_ALIGN)[0], likes)}
                                for names_b, likes in zip(self._physics.returned, self._returned_like)]
        """Per bucket, each returned leaf's name: (its first word in the bucket's words, its shape and dtype)."""
        self._leaf_at = {(bucket_of[k], names[k]): k for k in range(len(names))}
        """(bucket, leaf name): the leaf's position among the data's leaves, empty ones included (`field`)."""
        returned = {k for at in self._returned_at for k in at}
        p = self.placement  # laid out like `_tick`'s arguments and outputs, so that the types stay a fixed point
        self._split_leaves = [None if k in returned else np.asarray(x)
                              for k, x in enumerate(self._with_empty(self._data_leaves, lambda x: x))]
        """The data's leaves with None where the words hold them: the others are the same every tick."""
        model_paths = jax.tree_util.tree_flatten_with_path(self._models())[0]
        self._absent_models = [_NotGiven("model." + jax.tree_util.keystr(path[1:], simple=True, separator="."))
                               for path, _ in model_paths]
        self._words = [p.put_batched(pack_host_words([np.asarray(stable[k]) for k in at], OUTBOX_ALIGN))
                       for at in self._returned_at]
        shardings = (p.replicated, p.batched, p.batched, p.replicated, p.batched)  # tables, words, extra, flags, ...
        self._before = jax.jit(self._split_flat(self._before_all), donate_argnums=(2,), in_shardings=shardings,
                               out_shardings=p.batched)
        self._after = jax.jit(self._split_flat(self._after_all, keeps_words=True), donate_argnums=(2,),
                              in_shardings=shardings, out_shardings=p.batched)
        self._unpack = jax.jit(lambda words: [x for x in self._unpacked(words) if x.size])

    def _split_extra_types(self, extra: tuple[Tree, ...], inputs: tuple[Tree, ...]
                           ) -> tuple[tuple[Tree, ...], list[tuple[Callable[..., Any], tuple]]]:
        """The types of the extra state after a split tick from `extra` (`jax.eval_shape` of both halves, no
        compilation), so that its types are a fixed point from the first call on, as `_stable` makes them for the
        jitted tick; and both halves with the arguments they were traced with (`_ahead`, for `compile_ahead`).

        Why not the whole tick's `eval_shape`: under `streams` the data's types are the lanes' words', and tracing
        the physics and the backend's refresh (a whole forward) for the extra state's types alone took some 56 s of
        a 238 s engine build for the protocol's 141 buckets on an H200 (2026-12-03, stack samples). The arguments
        here have the types of the first tick's, mesh included, so that its call reuses these traces (JAX keys its
        trace cache on them) instead of tracing each half a second time."""
        flags = jax.ShapeDtypeStruct((4, sum(a.size for a in self.arrays)), jnp.int32,
                                     sharding=self.placement.replicated)  # as `_packed_flags` puts them
        strong = [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in jax.tree.leaves(extra)]  # as `_stable` gives them
        first = (self._table_leaves, self._words, strong, flags, inputs)
        found, before = jax.eval_shape(self._before, *first)
        outboxes = [jax.ShapeDtypeStruct(w.shape, w.dtype) for w in self._words]  # views of Warp's arrays
        second = (self._table_leaves, outboxes, found, flags, tuple(b[0] for b in before))
        found, _, _ = jax.eval_shape(self._after, *second)
        return jax.tree.unflatten(self._extra_def, found), [(self._before, first), (self._after, second)]

    def _unpacked(self, words: Sequence[jax.Array]) -> list[jax.Array]:
        """The data's leaves (`_split_leaves` filled in) from each bucket's words."""
        from dojo.backends.mjx.streams import OUTBOX_ALIGN, unpack_words

        leaves = list(self._split_leaves)
        for w, at, like in zip(words, self._returned_at, self._returned_like):
            for k, x in zip(at, unpack_words(w, like, OUTBOX_ALIGN)):
                leaves[k] = x
        return leaves

    def _split_flat(self, fn: Callable[..., tuple], keeps_words: bool = False) -> Callable[..., tuple]:
        """A half of the split tick as a function of (tables' leaves, each bucket's words, the extra state's
        leaves, the flags (`_packed_flags`), ...) returning (extra leaves, per bucket the rest of what `fn`
        returns) and with `keeps_words` a copy of the words: `fn` takes (models, tables, data, extra, members,
        resets, stepping, steps, ...) as `_flat`'s does, the four flags per bucket, and returns per bucket (extra,
        *rest). The models stand in as `_NotGiven` (a half reads the varying model rows from the tables,
        `_gathered`); the data is each bucket's words unpacked, and `_split_leaves`.

        Why a copy: the second half reads the lanes' outboxes through views, which the next tick's lanes
        overwrite; the engine keeps arrays of its own between ticks (one a bucket)."""
        def flat(tables: list, words: list, extra: list, flags: jax.Array, *args: Any) -> tuple:
            ends = np.cumsum([0] + [a.size for a in self.arrays])
            rows = [tuple(flags[k, start:end] for start, end in zip(ends, ends[1:])) for k in range(4)]
            members, steps = rows[0], rows[3]
            resets, stepping = (tuple(r.astype(bool) for r in row) for row in rows[1:3])
            out = fn(jax.tree.unflatten(self._model_def, self._absent_models),
                     jax.tree.unflatten(self._table_def, tables),
                     jax.tree.unflatten(self._data_def, self._unpacked(words)),
                     jax.tree.unflatten(self._extra_def, extra), members, resets, stepping, steps, *args)
            found, made = jax.tree.flatten(tuple(o[0] for o in out))
            if made != self._extra_def:
                raise TypeError(f"a tick changed the structure of its extra state: {made}")
            rest = tuple(o[1:] for o in out)
            return (found, rest, [jnp.copy(w) for w in words]) if keeps_words else (found, rest)

        return flat

    @property
    def data(self) -> tuple[Tree, ...]:
        """Each bucket's MJX data after the last tick (rebuilt from the leaves the tick keeps, once a tick; with
        `streams`, from each lane's words)."""
        if self._data is None:
            if self._data_leaves is None:
                self._data_leaves = self._unpack(self._words)
            self._data = jax.tree.unflatten(self._data_def, self._with_empty(self._data_leaves, lambda x: x))
        return self._data

    def field(self, bucket: int, name: str) -> jax.Array:
        """One data field of one bucket after the last tick (`qpos`, `qvel`, `_impl.nacon`: dotted into MJX's
        implementation data), as `data[bucket].<name>` holds it.
        With `streams` it is read out of the bucket's words alone, where `data` unpacks every leaf of every bucket
        in one program: a privileged policy reads two fields a bucket each tick, and that program's first call
        compiled for 10 s on 8 buckets on the CI machine (2026-12-03)."""
        from dojo.backends.mjx.streams import unpack_words, words_of

        if self._physics is None or self._data_leaves is not None or (bucket, name) not in self._leaf_at:
            return reduce(getattr, name.split("."), self.data[bucket])  # at hand already, or not a leaf of its own
        if name not in self._returned_words[bucket]:  # a leaf no tick changes, or an empty one
            return jnp.asarray(self._split_leaves[self._leaf_at[bucket, name]])
        start, like = self._returned_words[bucket][name]
        return unpack_words(self._words[bucket][start:start + words_of(like)], [like])[0]

    def _with_empty(self, kept: Sequence[Any], make: Callable[[Any], Any]) -> list:
        """The data's leaves in order: `kept` (the non-empty ones), and `make(empty array)` in the empty ones'
        places."""
        rest = iter(kept)
        return [make(self._data_empty[k]) if k in self._data_empty else next(rest)
                for k in range(self._data_def.num_leaves)]

    def _flat(self, fn: Callable[..., tuple]) -> Callable[..., tuple]:
        """`fn` of (models, tables, data, extra, ...), returning per bucket (data, extra, *rest), as a function of
        those four trees' leaves returning (data leaves, extra leaves, per bucket rest).

        Why: MJX's models and data are dataclasses that JAX flattens in Python, some 500 nodes for four buckets,
        on every call of a jitted function, hashing each NumPy field of a model (about 7 ms a call on the CI
        machine; on an H200 it held the GPU idle for most of a split tick's halves). Lists of arrays flatten in C++;
        the trees are rebuilt inside the trace, where it costs nothing per call."""
        def flat(models: list, tables: list, data: list, extra: list, *args: Any) -> tuple:
            rows = self.placement.count  # under `per_device` each device holds its share of every batch's rows
            data = self._with_empty(data, lambda x: jnp.zeros((x.shape[0] // rows, *x.shape[1:]), x.dtype))
            out = fn(jax.tree.unflatten(self._model_def, models), jax.tree.unflatten(self._table_def, tables),
                     jax.tree.unflatten(self._data_def, data), jax.tree.unflatten(self._extra_def, extra), *args)
            data, data_def = jax.tree.flatten(tuple(o[0] for o in out))
            extra, extra_def = jax.tree.flatten(tuple(o[1] for o in out))
            for what, made, kept in (("data", data_def, self._data_def), ("extra state", extra_def, self._extra_def)):
                if made != kept:  # the leaves would be read back under the wrong fields
                    raise TypeError(f"a tick changed the structure of its {what}: {made}")
            if any(data[j].size for j in self._data_empty):  # dropped below, so it would be read back empty
                raise TypeError("a tick changed the structure of its data: an array where it had an empty one")
            return [x for j, x in enumerate(data) if j not in self._data_empty], extra, tuple(o[2:] for o in out)

        return flat

    def _models(self) -> tuple[Tree, ...]:
        return tuple(a.mx for a in self.arrays)

    def _tables(self) -> tuple[dict[str, jax.Array], ...]:
        return tuple(a.table for a in self.arrays)

    def _flags(self) -> tuple[tuple[jax.Array, ...], ...]:
        z = [(jnp.zeros(a.size, jnp.int32), jnp.zeros(a.size, bool), jnp.zeros(a.size, bool),
              jnp.zeros(a.size, jnp.int32)) for a in self.arrays]
        return tuple(tuple(col) for col in zip(*z))

    def _tick_all(self, mxs: tuple, tables: tuple, data: tuple, extra: tuple, members: tuple, resets: tuple,
                  stepping: tuple, inputs: tuple, steps: tuple) -> tuple:
        return tuple(_bucket_tick(a, self.hooks, *args)
                     for a, *args in zip(self.arrays, mxs, tables, data, extra, members, resets, stepping, inputs,
                                         steps))

    def _before_all(self, mxs: tuple, tables: tuple, data: tuple, extra: tuple, members: tuple, resets: tuple,
                    stepping: tuple, steps: tuple, inputs: tuple) -> tuple:
        """The tick up to the physics (`streams`): per bucket the extra state, the controls' aux outputs and what
        its lane loads (`streams.exchange_fields`: the controls, the state after the resets, the environments'
        rows of the varying model fields, which environments step) packed into one flat array."""
        from dojo.backends.mjx.streams import exchange_fields, pack_words

        out = []
        for a, mx, table, d, e, member, reset, step, given, batched in zip(
                self.arrays, mxs, tables, data, extra, members, resets, stepping, inputs, self._physics.batched):
            a, m, rows = _gathered(a, mx, table, member)
            _, driven, e, aux = _before_physics(a, self.hooks, m, table, d, e, member, reset, step, given)
            lane = {"data": lambda name: getattr(driven, name), "model": rows.__getitem__,
                    "lane": lambda _: step.astype(jnp.int32)}
            out.append((e, aux, pack_words([lane[owner](name) for owner, name in exchange_fields(batched)])))
        return tuple(out)

    def _after_all(self, mxs: tuple, tables: tuple, data: tuple, extra: tuple, members: tuple, resets: tuple,
                   stepping: tuple, steps: tuple, aux: tuple) -> tuple:
        """The tick after the physics (`streams`): each bucket's data as its lane returned it (stepped, the
        environments that do not step put back, and what the observations read brought up to date, as
        `_after_physics` does with the backend's `Hooks.refresh`), observed."""
        out = []
        for a, mx, table, d, e, member, reset, step, x, k in zip(
                self.arrays, mxs, tables, data, extra, members, resets, stepping, aux, steps):
            a, m, _ = _gathered(a, mx, table, member)
            out.append(self.hooks.observe(a, m, d, e, member, reset, step, x, k))
        return tuple(out)

    def _packed_flags(self, members: Sequence[Any], resets: Sequence[Any], stepping: Sequence[Any],
                     steps: Sequence[Any]) -> jax.Array:
        """A split tick's per-environment flags, every bucket's end to end, as one int32 array [4, envs] (member,
        reset, stepping, step) put on the device in one transfer: converting four arrays a bucket one by one was
        most of the host's time in a tick outside its halves (1.7 of 2.1 ms at 12 toy buckets on the CI machine)."""
        rows = [np.concatenate([np.asarray(v, np.int32).reshape(-1) for v in row])
                for row in (members, resets, stepping, steps)]
        return jax.device_put(np.stack(rows), self.placement.replicated)

    def tick(self, members: Sequence[Any], resets: Sequence[Any], stepping: Sequence[Any], inputs: Sequence[Tree],
             steps: Sequence[Any] | None = None) -> tuple[Tree, ...]:
        """Advance every bucket by one control step. Without `streams` nothing waits for the device (the outputs
        are computed asynchronously); with `streams` the tick returns when they are."""
        return self.start_tick(members, resets, stepping, inputs, steps)()

    def start_tick(self, members: Sequence[Any], resets: Sequence[Any], stepping: Sequence[Any],
                   inputs: Sequence[Tree], steps: Sequence[Any] | None = None) -> Callable[[], tuple[Tree, ...]]:
        """`tick` in two parts, so that the lanes of several engines run at once (`EngineGroups`): this starts the
        tick and returns the call that ends it and gives its outputs. Without `streams` it starts the whole tick;
        with `streams` it runs the first jitted half and launches the lanes of the buckets where an environment
        resets or steps (`StreamPhysics.launch`), and the call waits for the lanes and
        runs the second half, each half waited for (with `split_ms`, the three parts' milliseconds are kept)."""
        steps = steps if steps is not None else [np.zeros(a.size, np.int32) for a in self.arrays]
        inputs = tuple(jax.tree.map(jnp.asarray, i) for i in inputs)
        call = run_settled if may_capture(self.impl, self._graphs, self._ticks) else _call
        if self._physics is None:
            self._data_leaves, self._extra_leaves, rest = call(
                self._tick, self._model_leaves, self._table_leaves, self._data_leaves, self._extra_leaves,
                tuple(jnp.asarray(m, jnp.int32) for m in members), tuple(jnp.asarray(r, bool) for r in resets),
                tuple(jnp.asarray(s, bool) for s in stepping), inputs, tuple(jnp.asarray(s, jnp.int32) for s in steps))
            self._ticks += 1
            self._data = None
            out = tuple(r[0] for r in rest)
            return lambda: out
        flags = self._packed_flags(members, resets, stepping, steps)
        times = [time.perf_counter()]
        extra, before = wait_for(call(self._before, self._table_leaves, self._words, self._extra_leaves, flags,
                                      inputs))
        times.append(time.perf_counter())
        self._physics.launch([b[1] for b in before], [bool(np.any(r)) or bool(np.any(s))
                                                      for r, s in zip(resets, stepping)])

        def finish() -> tuple[Tree, ...]:
            outboxes = self._physics.finish()
            times.append(time.perf_counter())
            self._extra_leaves, out, self._words = wait_for(call(self._after, self._table_leaves, outboxes, extra,
                                                                 flags, tuple(b[0] for b in before)))
            times.append(time.perf_counter())
            if self.split_ms is not None:
                for kept, start, end in zip(self.split_ms.values(), times, times[1:]):
                    kept.append(1e3 * (end - start))
            self._data_leaves = None  # unpacked from the lanes' words when `data` is read
            self._ticks += 1
            self._data = None
            return tuple(r[0] for r in out)

        return finish

    def wait_for_lanes(self) -> None:
        """With `streams`, wait for lanes that a tick launched and nothing finished (a run interrupted between
        `start_tick` and its end, as `EngineGroups.tick` can be): their copies read the tick's JAX buffers and write
        the lanes' outboxes, so the engine is not let go while they run. Why: an interrupted protocol run on an
        H200 died in its teardown (2026-12-03, `terminate called after throwing an instance of '7'`), after its
        results were stored."""
        if self._physics is not None:
            self._physics.engine.synchronize()

    def lane_ticks(self) -> tuple[int, int]:
        """With `streams`, (lane ticks launched, lane ticks left out because the lane's environments were all
        idle) since the engine was built; (0, 0) without."""
        if self._physics is None:
            return 0, 0
        return self._physics.engine.lane_ticks, self._physics.engine.idle_ticks

    def lane_ms(self, ticks: int = 5) -> list[dict[str, Any]]:
        """With `streams`, each lane's tick on its own (`StreamEngine.lane_ms`: tasks, environments, median ms of
        `ticks`); without, [] (the jitted tick has no lanes)."""
        return self._physics.engine.lane_ms(ticks) if self._physics is not None else []

    def kernel_ms(self, top: int = 12) -> list[dict[str, Any]]:
        """With `streams`, per lane the GPU time of its tick kernel by kernel (`StreamEngine.kernel_ms`); without,
        [] (the jitted tick's Warp calls run inside XLA's program)."""
        return self._physics.engine.kernel_ms(top) if self._physics is not None else []

    def overflows(self) -> dict[str, dict[str, int]]:
        """{bucket key: {what overflowed: worlds}} since the engine was built (warp only; reads the device).

        Warp keeps contacts and constraint rows in preallocated buffers and drops what does not fit; it sets a
        sticky per-world bit when it does, which this reads. The `jax` implementation allocates every candidate
        contact statically and cannot overflow. With `streams` the lanes run all the physics and this reads their
        bits (the data's are a copy of them), without unpacking the data: the backend checks after every tick.
        """
        if self._physics is not None:
            return self._physics.engine.overflows()
        found = {}
        for arr, data in zip(self.arrays, self.data):
            bits = getattr(getattr(data, "_impl", None), "overflow", None)
            flags = decode_overflow(jax.device_get(bits)) if bits is not None else {}
            if flags:
                found[arr.bucket.key] = flags
        return found

    def check_overflow(self) -> None:
        """Raise `CapacityOverflow` naming each bucket, buffer and world count if any Warp buffer overflowed."""
        raise_overflow(self.overflows(), self.arrays)

    def compilations(self) -> int:
        """How many programs the tick has compiled (1 in a healthy run, whatever the refills; with `streams`, the
        most either half has)."""
        if self._physics is not None:
            return max(self._before._cache_size(), self._after._cache_size())
        return self._tick._cache_size()


PROGRAM_BUCKETS = 16
"""At most this many buckets share one jitted program (`make_engine`). XLA's compile of one program over every
bucket grows faster than the buckets do. Measured on the CI machine (2026-12-02, `dojo run backend=mjx
backend.impl=warp policy=zero suite=robodojo_sim seeds=[0]` with `JAX_LOG_COMPILES=1`, so the physics is Warp's and
the program is the tick's resets, actions, predicates and observations): 7 tasks' 28 plans in 13 buckets traced in
3.7 s and compiled in 13.3 s; the suite's 850 plans that the mjx backend runs, 141 buckets, traced in 56 s and then
ran the 23 GB machine out of memory (24 GB resident) before their one program had compiled."""


class EngineGroups:
    """`Engine`'s interface over buckets in groups of at most `per_program`, one `Engine` (one jitted tick, or two
    halves with `streams`) each: each group compiles on its own, so the compile grows with the groups rather than
    with the whole program, and a group that recurs (the same buckets at the same sizes) is found in JAX's
    compilation cache.

    What it costs: a tick launches one program a group instead of one. Without `streams` nothing waits, so the
    device queues them as it queued the buckets of one program. With `streams` each group's first half runs and
    launches its lanes while the next group's first half runs, and the second halves run once every lane has
    finished, so the lanes of every group overlap as they do in one engine."""

    def __init__(self, buckets: Sequence[Bucket], sizes: Sequence[int], impl: str, hooks: Hooks | None = None,
                 example_inputs: Sequence[Tree] | None = None, placement: Placement | None = None,
                 graph_mode: object | None = None, streams: bool = False, per_program: int = PROGRAM_BUCKETS):
        self.hooks = hooks or Hooks()
        self._cuts = [(k, min(k + per_program, len(buckets))) for k in range(0, len(buckets), per_program)]
        self.engines: list[Engine] = []
        for a, b in self._cuts:  # minutes at a suite's scale (406 s for 141 buckets on streams): say how far it is
            start = time.perf_counter()
            self.engines.append(Engine(buckets[a:b], sizes[a:b], impl, self.hooks,
                                       None if example_inputs is None else example_inputs[a:b], placement,
                                       graph_mode, streams))
            log.info("mjx backend: engine group %d of %d built (buckets %d-%d of %d, %.1f s)", len(self.engines),
                     len(self._cuts), a + 1, b, len(buckets), time.perf_counter() - start)
        self.arrays = [arr for engine in self.engines for arr in engine.arrays]

    @property
    def data(self) -> tuple[Tree, ...]:
        """Every bucket's data, in the buckets' order."""
        return tuple(d for engine in self.engines for d in engine.data)

    def field(self, bucket: int, name: str) -> jax.Array:
        """`Engine.field` of the group that holds bucket number `bucket`."""
        for engine, (a, b) in zip(self.engines, self._cuts):
            if a <= bucket < b:
                return engine.field(bucket - a, name)
        raise IndexError(f"bucket {bucket} of {self._cuts[-1][1]}")

    def tick(self, members: Sequence[Any], resets: Sequence[Any], stepping: Sequence[Any], inputs: Sequence[Tree],
             steps: Sequence[Any] | None = None) -> tuple[Tree, ...]:
        """`Engine.tick` of every group on its buckets' share of the arguments, every group started before any is
        ended (`Engine.start_tick`), so that with `streams` every group's lanes run at once; the outputs in the
        buckets' order."""
        ends = [engine.start_tick(members[a:b], resets[a:b], stepping[a:b], inputs[a:b],
                                  None if steps is None else steps[a:b])
                for engine, (a, b) in zip(self.engines, self._cuts)]
        return tuple(out for end in ends for out in end())

    def wait_for_lanes(self) -> None:
        """`Engine.wait_for_lanes` of every group."""
        for engine in self.engines:
            engine.wait_for_lanes()

    def lane_ticks(self) -> tuple[int, int]:
        """`Engine.lane_ticks` summed over the groups."""
        counts = [engine.lane_ticks() for engine in self.engines]
        return sum(c[0] for c in counts), sum(c[1] for c in counts)

    def overflows(self) -> dict[str, dict[str, int]]:
        """Every group's `Engine.overflows`, in one map (bucket keys are unique across groups)."""
        return {key: flags for engine in self.engines for key, flags in engine.overflows().items()}

    def check_overflow(self) -> None:
        """`Engine.check_overflow` over every group at once, so that the error names every bucket that overflowed."""
        raise_overflow(self.overflows(), self.arrays)

    def compilations(self) -> int:
        """The most programs any group has compiled (1 in a healthy run)."""
        return max(engine.compilations() for engine in self.engines)


def make_engine(buckets: Sequence[Bucket], sizes: Sequence[int], impl: str, hooks: Hooks | None = None,
                example_inputs: Sequence[Tree] | None = None, placement: Placement | None = None,
                graph_mode: object | None = None, streams: bool = False,
                per_program: int | None = None) -> Engine | EngineGroups:
    """One `Engine` for up to `per_program` buckets (`PROGRAM_BUCKETS` when None), else `EngineGroups`; either
    with the programs of its first tick compiled (`compile_ahead`)."""
    limit = PROGRAM_BUCKETS if per_program is None else int(per_program)
    if limit < 1:
        raise ValueError(f"backend.program_buckets must be at least 1, got {limit}")
    if len(buckets) <= limit:
        engine = Engine(buckets, sizes, impl, hooks, example_inputs, placement, graph_mode, streams)
    else:
        engine = EngineGroups(buckets, sizes, impl, hooks, example_inputs, placement, graph_mode, streams, limit)
    compile_ahead(engine.engines if isinstance(engine, EngineGroups) else [engine])
    return engine


def compile_ahead(engines: Sequence[Engine], threads: int | None = None) -> None:
    """Compile the programs of every engine's first tick (`Engine._ahead`) at once, on up to `threads` threads
    (when None: the machine's cores where the engines run on GPUs, one on a CPU): each is lowered here, in turn,
    and compiled by XLA on a thread of its own, so that the groups of a suite (`EngineGroups`) compile side by side;
    their first tick then finds them compiled (JAX keeps what `Lowered.compile` made for the jitted call of the same
    arguments' types). On a CPU one at a time: there XLA's compile of a real task's jitted tick (`impl=jax`) takes
    gigabytes, and the 2-core CI machine gained nothing from two threads.

    Why: a first tick compiled its groups' programs one after another, each when its group's turn came: 58 of the
    91 s of the protocol's first tick on streams on an H200 (2026-12-03, 9 groups, 18 programs, stack samples),
    on a host of 16 cores. Arguments of other types than those given here (a backend's inputs that differ from its
    example) compile again at the first tick, as they would have without this."""
    lowered = [jitted.lower(*args) for engine in engines for jitted, args in engine._ahead]
    for engine in engines:
        engine._ahead = []  # its arrays (the jitted tick's data) are donated by the first tick
    if not lowered:
        return
    start = time.perf_counter()
    if threads is None:
        threads = (os.cpu_count() or 1) if engines[0].placement.on_gpu else 1
    workers = max(1, min(len(lowered), threads))
    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(lambda program: program.compile(), lowered))
    log.info("mjx backend: %d program(s) of the first tick compiled on %d thread(s) (%.1f s)", len(lowered),
             workers, time.perf_counter() - start)
