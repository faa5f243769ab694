"""Every bucket's physics on its own CUDA stream: the buckets of a tick run concurrently on the GPU.

Why. `Engine` traces all buckets of a tick into one jitted program, but MJX's Warp calls are ordered by a token,
so the device runs the buckets one after another, and a MuJoCo Warp step of a few hundred worlds costs about the
same as one of thousands (its hundreds of small kernels are latency-bound). Measured on one H100 (2026-11-25,
`dojo bench sim backend.impl=warp`, 12 tasks in 14 buckets): the mix ran 289k physics steps/s at 4,096 envs
(bucket by bucket, one jitted call each: 323k), 837k at 16,384, while `stack_blocks` alone ran 3.91M at 16,384:
about 1 ms per bucket and sub-step whatever its size.

How. `StreamEngine` drives MuJoCo Warp directly (the copy MJX vendors, so the kernels and their on-disk cache are
MJX's): per bucket one `Model` with the varying fields batched per world (`put_model(batch_sizes=...)`, world i
holds member i mod n, as `dojo bench sim` assigns them), one `Data`, its own stream, and one CUDA graph per
control input holding "copy the controls, then `n_substeps` steps". A tick launches each bucket's graph on its own
stream: independent kernels of different buckets overlap instead of queueing. Contact and constraint buffers are
sized like `Engine`'s (`contact_capacity`) and overflow is checked the same way (`check_overflow`).

Measured (same H100, same day, `modes=[heterogeneous,homogeneous,streams]`): the mix at 4,096 envs ran 890k
physics steps/s concurrently against 320k for the same graphs on one stream (2.78x) and 314k for `Engine`; at
16,384, 1.49M against 837k (1.78x) and 823k. One bucket alone gains nothing (`stack_blocks`: 3.90M either way):
the gain is the overlap of buckets, largest where they are small. Those figures were taken before the lanes used
the plans' solver tolerance (MuJoCo Warp's `put_model` raises it from 1e-8 to 1e-6, which MJX, so `Engine`, does
not): concurrent against serial compares like with like, but against `Engine` part of the gap may have been
fewer solver iterations. Not yet measured again on a GPU.

Scope. `StreamEngine` is physics only (the `streams` and `merged_streams` modes of `dojo bench sim`): no resets,
predicates or observations. `StreamPhysics` puts it under `Engine` (`backend.streams`): the jitted tick's resets,
actions and observations around the lanes' physics. Needs warp-lang; on Warp's CPU device (no streams, no
graphs) each tick launches the steps one bucket after another, which is how CI checks that this engine steps
exactly what `Engine` steps (`tests/backends_mjx/test_streams_cpu.py`: bit for bit). A varying field MuJoCo Warp
cannot batch per world keeps member 0's value and is listed in the figures (`unbatched_fields`); so far that is
only `dof_M0`, which MJX's model has and MuJoCo Warp's step never reads.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from dojo.backends.mjx.batch import STATE_FIELDS, CapacityOverflow, contact_capacity, decode_overflow
from dojo.backends.mjx.bucket import Bucket
from dojo.backends.mjx.capture import collector_held

log = logging.getLogger(__name__)


def batchable_fields(names: Sequence[str]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(fields MuJoCo Warp can hold per world, fields it cannot) among the model field names given."""
    from mujoco.mjx.third_party.mujoco_warp._src import types as mjw_types
    from mujoco.mjx.third_party.mujoco_warp._src import warp_util

    specs = {f.name: f.type for f in dataclasses.fields(mjw_types.Model) if warp_util.is_array_spec(f.type)}
    ok = tuple(n for n in names if getattr(specs.get(n), "shape", ("",))[:1] == ("*",))
    return ok, tuple(n for n in names if n not in ok)


def world_values(bucket: Bucket, size: int, name: str) -> np.ndarray:
    """A varying field's value for each of `size` worlds (world i holds member i mod n), float32."""
    rows = bucket.table()[name]
    return np.ascontiguousarray(rows[np.arange(size) % len(rows)], dtype=np.float32)


Copy = tuple[Any, Any, int, int, int]
"""`wp.copy(dest, src, dest_offset, src_offset, count)`'s arguments, on flat views of 32-bit words (`_words`)."""


def _scalar_type(array: Any) -> Any:
    """The Warp scalar type `array`'s elements are made of (float32 for a vec3 or a mat33)."""
    return getattr(array.dtype, "_wp_scalar_type_", array.dtype)


def _word_count(wp: Any, array: Any) -> int | None:
    """How many 32-bit words contiguous Warp `array` holds, if its elements are made of 32-bit scalars (None
    otherwise)."""
    if wp.types.type_size_in_bytes(_scalar_type(array)) != 4 or not array.is_contiguous:
        return None
    return array.size * wp.types.type_size_in_bytes(array.dtype) // 4


def _view(wp: Any, base: Any, at: int, dtype: Any, shape: tuple[int, ...]) -> Any:
    """A Warp array of `dtype` and `shape` over `base`'s memory from its 32-bit word `at` on, owning nothing:
    `base` must outlive it."""
    return wp.array(ptr=base.ptr + 4 * at, dtype=dtype, shape=shape, device=base.device, copy=False)


def _words(wp: Any, array: Any) -> Any:
    """A flat float32 view of contiguous Warp `array`, whose elements are made of 32-bit scalars, so that one copy
    moves any of its fields' values (floats, ints, vectors, matrices) as words."""
    count = _word_count(wp, array)
    if count is None:
        raise ValueError(f"a lane exchanges contiguous arrays of 32-bit scalars, not {array.dtype} {array.shape}")
    return _view(wp, array, 0, wp.float32, (count,))


def inbox_words(size: int, itemsize: int) -> int | None:
    """How many words an array of `size` scalars of `itemsize` bytes takes in a lane's inbox: one a scalar of 32
    bits, four bytes to a word for 1-byte scalars (flags such as `light_active`, which the random setting's lights
    vary per plan), None for other widths."""
    return size if itemsize == 4 else -(-size // 4) if itemsize == 1 else None


def _byte_view(wp: Any, base: Any, at: int, count: int) -> Any:
    """`count` bytes of `base`'s memory from its byte `at` on, as uint8, owning nothing."""
    return wp.array(ptr=base.ptr + at, dtype=wp.uint8, shape=(count,), device=base.device, copy=False)


def _inbox(wp: Any, arrays: Sequence[Any]) -> tuple[Any, list[Copy]]:
    """A flat buffer of words holding `arrays` end to end in order, and the copies from it into them (a lane's
    inbox): arrays of 32-bit scalars as words, of 1-byte scalars as bytes (`inbox_words`; `pack_words` lays them
    out alike). Empty arrays take no room; other widths are refused by dtype."""
    laid = []  # (array, its words, whether copied as bytes)
    for array in (array for array in arrays if array.size):
        count = _word_count(wp, array)
        as_bytes = count is None and array.is_contiguous and wp.types.type_size_in_bytes(array.dtype) == 1
        if count is None and not as_bytes:
            raise ValueError(f"a lane exchanges contiguous arrays of 32-bit or 1-byte scalars, not {array.dtype} "
                             f"{array.shape}")
        laid.append((array, inbox_words(array.size, 1) if as_bytes else count, as_bytes))
    offsets, total = word_offsets([count for _, count, _ in laid])
    buffer = wp.zeros(total, dtype=wp.float32)
    copies: list[Copy] = []
    for (array, count, as_bytes), at in zip(laid, offsets):
        if as_bytes:  # exactly the field's bytes, not the last word's padding
            copies.append((_byte_view(wp, array, 0, array.size), _byte_view(wp, buffer, 4 * at, array.size),
                           0, 0, array.size))
        else:
            copies.append((_words(wp, array), buffer, 0, at, count))
    return buffer, copies


OUTBOX_ALIGN = 64
"""Words (256 bytes) to which each field housed in a lane's outbox is aligned: what Warp's CUDA allocator gives
every array (on Warp's CPU device 64 bytes), so that a field keeps the alignment its kernels test before vector
loads (`wp.tile_load`)."""


def word_offsets(counts: Sequence[int], align: int = 1) -> tuple[list[int], int]:
    """(where each of arrays of `counts` words starts in a flat buffer holding them in order, each start a
    multiple of `align` words; the buffer's length). An empty array takes no room."""
    offsets, at = [], 0
    for count in counts:
        if count:
            at = -(-at // align) * align
        offsets.append(at)
        at += count
    return offsets, at


def _house(wp: Any, data: Any, names: Sequence[str]) -> Any:
    """One flat buffer of words (`word_offsets`, `OUTBOX_ALIGN`) holding the data arrays `names` (as `lane_array`
    finds them), each rebound in `data` to a view of its place in the buffer with its value kept: the lane's
    data lives in its outbox, so no copies out end its tick.

    Why: a tick's graph copied some 145 fields a lane into the outbox at its end: about 5% of a lane's
    2,650 graph nodes a tick on the 24-task mix. On an H200 (2026-12-02, the 24-task mix merged at 1,200
    environments) the tick went from 272.3k to 279.1k physics steps/s (README, speed)."""
    arrays = [lane_array(wp, data, name) for name in names]
    offsets, total = word_offsets([_word_count(wp, array) for array in arrays], OUTBOX_ALIGN)
    buffer = wp.zeros(total, dtype=wp.float32)
    for name, array, at in zip(names, arrays, offsets):
        if array.size:
            view = _view(wp, buffer, at, array.dtype, array.shape)
            wp.copy(view, array)
            owner, field = _owner(data, name)
            setattr(owner, field, view)
    return buffer


@dataclass
class _Program:
    """What a lane's graph runs for one control input: the copies in (the controls; under `StreamPhysics` every
    field a tick loads), the sub-steps, then with `restores` the state of the worlds that do not step put back
    (`lane_kernels.keep_unstepped`'s arguments, one launch per state field) and a refresh at the state each world
    holds (`refresh`; under `StreamPhysics` the data it leaves is the lane's outbox, `_house`)."""

    loads: list[Copy]
    restores: list[tuple[Any, int, Any, Any]] = dataclasses.field(default_factory=list)


def _control_step(wp: Any, mjw: Any, model: Any, data: Any, program: _Program, substeps: int) -> None:
    """One tick of one bucket: `program` around `substeps` physics steps."""
    for copy in program.loads:
        wp.copy(*copy)
    for _ in range(substeps):
        mjw.step(model, data)
    if program.restores:
        from dojo.backends.mjx.lane_kernels import keep_unstepped

        for stepping, width, field, saved in program.restores:
            wp.launch(keep_unstepped, dim=field.size, inputs=[stepping, width, field, saved])
        refresh(wp, mjw, model, data)


def refresh(wp: Any, mjw: Any, model: Any, data: Any) -> None:
    """What the tick's readers take from a lane, brought up to date at the state each world holds after the
    sub-steps and the restores: the poses of bodies, geoms, sites, cameras and lights, tendon lengths
    (`fwd_kinematics`), tendon speeds (`lane_kernels.tendon_velocity`) and contacts (`collision`), each as MuJoCo
    Warp's forward computes it. The rest of a forward is left as the last sub-step computed it, at the state
    before that sub-step's integration: inertia, constraint rows and forces (`efc_*`, `nefc`, and the contacts'
    `efc_address`, which then points into rows built for the last sub-step's contacts, not these), actuator
    lengths, moments and forces, accelerations, sensors and their history. So the data mixes two states, unlike
    MuJoCo's after `mj_step` (all of it before the integration): nothing the backend reads (`_DeviceHooks.observe`,
    the renderer) comes from the stale part, a reader of contact forces would have to refresh it first, and the
    next tick's first step recomputes all of it before reading any (tested against a whole forward, bit for bit, on
    Warp's CPU device).

    Why not the whole forward: on the GPU a lane's tick is bound by its kernels (README, speed), and a forward
    launches 102-105 kernels on `stack_blocks` and `put_bottles_into_dustbin` against 25-28 for this
    (`warp_launches.recorded_tick`, `dojo bench kernels`), the solver's, the heaviest, among those left out."""
    if model.opt.enableflags & mjw.EnableBit.SLEEP and not model.opt.disableflags & mjw.DisableBit.ISLAND:
        mjw.forward(model, data)  # sleeping bodies take two collision passes and the islands between them
        return
    mjw.fwd_kinematics(model, data)
    if model.opt.run_collision_detection:
        mjw.collision(model, data)
    if model.ntendon:
        from dojo.backends.mjx.lane_kernels import tendon_velocity

        wp.launch(tendon_velocity, dim=(data.nworld, model.ntendon),
                  inputs=[model.ten_J_rownnz, model.ten_J_rowadr, model.ten_J_colind, data.qvel, data.ten_J],
                  outputs=[data.ten_velocity])


def _capture(wp: Any, mjw: Any, stream: Any, model: Any, data: Any, program: _Program, substeps: int) -> Any:
    """One CUDA graph of `_control_step`, captured with Python's garbage collector held back (`capture`: nothing
    may be freed while a stream captures)."""
    with collector_held(), wp.ScopedCapture(stream=stream, force_module_load=False) as capture:
        _control_step(wp, mjw, model, data, program, substeps)
    return capture.graph


CAPTURE_LOADS_FROM = (12, 3)
"""The CUDA driver from which a stream capture may load modules (Warp's `capture_begin` relies on it too)."""


def capture_loads_modules(wp: Any) -> bool:
    """Whether this machine's CUDA driver loads (and on a cold cache compiles) Warp modules inside a graph capture,
    so that a lane captures straight away, as MuJoCo Warp's own viewer does; on older drivers `_load_kernels` runs
    first. Why skip it where it can be skipped: it is one eager physics step per lane, each of its hundred-odd
    launches a Python call, and it took 20 of the 144 s the 141 lanes of the protocol took to build on an H200
    (2026-12-03, stack samples)."""
    driver = wp.get_cuda_driver_version()
    return driver is not None and tuple(driver) >= CAPTURE_LOADS_FROM


def _load_kernels(wp: Any, mjw: Any, model: Any, data: Any, program: _Program) -> None:
    """One physics step, and where `program` ends its tick with restores and a refresh those kernels too, so that
    every kernel the graphs will hold is loaded (compiled on a cold cache: a capture on a CUDA driver older than
    12.3 cannot load modules), with the state put back afterwards: the first tick starts from the initial state."""
    kept = {name: wp.clone(getattr(data, name)) for name in STATE_FIELDS}
    mjw.step(model, data)
    if program.restores:
        from dojo.backends.mjx import lane_kernels

        wp.load_module(lane_kernels, device=data.qpos.device)
        refresh(wp, mjw, model, data)
    for name, value in kept.items():
        wp.copy(getattr(data, name), value)


def _owner(data: Any, name: str) -> tuple[Any, str]:
    """(the MuJoCo Warp struct, its attribute) that hold the data field behind an MJX data leaf named as
    `jax.tree_util.keystr` names it (`qpos`, `_impl.M`, `_impl.contact__geom`: MJX flattens MuJoCo Warp's nested
    structs with `__`); (None, ...) if there is no such struct."""
    *path, field = name.removeprefix("_impl.").split("__")
    for part in path:
        data = getattr(data, part, None)
    return data, field


def lane_array(wp: Any, data: Any, name: str) -> Any:
    """The MuJoCo Warp data array behind an MJX data leaf (named as `_owner` takes it), None if it has none."""
    owner, field = _owner(data, name)
    found = getattr(owner, field, None)
    return found if isinstance(found, wp.array) else None


@dataclass
class _Lane:
    """One bucket on the device: model, data, stream, and per control input the copies around its sub-steps and
    (on a GPU) their captured graph."""

    bucket: Bucket
    size: int
    model: Any
    data: Any
    stream: Any
    graphs: list[Any]
    programs: list[_Program]
    """Per control input, what runs around the sub-steps (the graphs hold the addresses it names: those buffers
    live as long as the lane)."""
    sources: list[Any]
    """The control batches the copies in read, without `exchange`."""
    batched: tuple[str, ...]
    """The bucket's varying model fields this lane holds per world (`batchable_fields`)."""
    inbox: Any = None
    """With `exchange`: the flat words a tick loads (`exchange_fields`' order), one copy from the first half."""
    outbox: Any = None
    """With `exchange`: the flat words that house the `returned` fields (`_house`: the data's arrays are views
    of it), which after the sub-steps and a refresh the second half reads."""
    returned: tuple[str, ...] = ()
    """With `exchange`: the MJX data leaves (named as `lane_array` takes them) the outbox holds, in its order."""
    stepping: Any = None
    """With `exchange`: int32 per world, whether its environment steps this tick (loaded with the inbox)."""


LOADED_FIELDS = tuple(name for name in STATE_FIELDS if name != "ctrl") + ("mocap_pos", "mocap_quat", "geom_xpos",
                                                                         "geom_xmat")
"""What a tick's physics takes from the jitted half before it, besides the controls: the state, the mocap bodies'
poses and the geom poses (a reset sets fixtures' poses, which MuJoCo Warp's step never recomputes)."""


def exchange_fields(batched: Sequence[str]) -> tuple[tuple[str, str], ...]:
    """What a tick loads into a lane with `exchange`, in its inbox's order: ("data", name) for the controls and
    `LOADED_FIELDS`, ("model", name) for the environments' rows of the batched varying fields `batched`, and
    ("lane", "stepping"), whether each environment steps (int32)."""
    return (("data", "ctrl"), *(("data", name) for name in LOADED_FIELDS), *(("model", name) for name in batched),
            ("lane", "stepping"))


def pack_words(arrays: Sequence[Any], align: int = 1) -> Any:
    """JAX arrays of 32-bit or 1-byte elements as one flat float32 array, in order with their bits kept, each
    starting at a multiple of `align` words (`word_offsets`; zeros between), 1-byte elements four to a word
    (`inbox_words`): what a lane's inbox takes in one copy (`align` 1), or its outbox holds (`OUTBOX_ALIGN`)."""
    import jax.numpy as jnp

    offsets, _ = word_offsets([words_of(a) for a in arrays], align)
    parts, at = [], 0
    for a, start in zip(arrays, offsets):
        if a.size:
            if start > at:
                parts.append(jnp.zeros(start - at, jnp.float32))
            parts.append(_as_words(a))
            at = start + words_of(a)
    return jnp.concatenate(parts) if parts else jnp.zeros(0, jnp.float32)


def pack_host_words(arrays: Sequence[np.ndarray], align: int = 1) -> np.ndarray:
    """`pack_words` on the host: the same words, bit for bit, from numpy arrays. Why: an engine's first words are
    packed once per bucket outside any jitted function, where `pack_words` ran some 500 eager JAX operations a
    bucket, each a program of its own shapes to compile or look up (6-8 s of every 16 buckets' 30 s set-up on an
    H200, 2026-12-03); here it is a few copies."""
    offsets, total = word_offsets([words_of(a) for a in arrays], align)
    words = np.zeros(total, np.float32)
    for a, start in zip(arrays, offsets):
        if a.size:
            flat = np.ascontiguousarray(a).reshape(-1)
            if flat.dtype.itemsize == 1:  # bool as 0/1, int8 as its two's-complement byte, four to a word
                flat = np.pad(flat.astype(np.uint8), (0, -flat.size % 4))
            words[start:start + words_of(a)] = flat.view(np.float32)
    return words


def unpack_words(words: Any, like: Sequence[Any], align: int = 1) -> list[Any]:
    """Flat float32 words laid out as `pack_words(..., align)` lays out arrays shaped like `like`, as those arrays
    of their dtypes with their bits kept. The words are bitcast once per element type and each such view cut into
    every part at once (`lax.split`): the halves unpack some 150 leaves a bucket, and a slice, a bitcast and a
    reshape per leaf, each traced through `jnp`, took 1.7 of the 7.1 s that 16 protocol buckets' engine took to
    build on the CI machine (2026-12-03, cProfile)."""
    import jax
    import jax.numpy as jnp

    offsets, _ = word_offsets([words_of(a) for a in like], align)
    sizes: list[int] = []  # words of each stretch in order, the gaps between parts and after the last included
    index: list[int] = []  # the stretch that holds each of `like`
    at = 0
    for a, start in zip(like, offsets):
        if start > at:
            sizes.append(start - at)
        index.append(len(sizes))
        sizes.append(words_of(a))
        at = start + sizes[-1]
    if words.shape[0] > at:
        sizes.append(words.shape[0] - at)
    views: dict[Any, list[Any]] = {}

    def stretches(dtype: Any) -> list[Any]:
        """The stretches of the words as elements of `dtype` (a 4-byte type, or uint8: four to a word)."""
        if dtype not in views:
            view = words if dtype == jnp.float32 else jax.lax.bitcast_convert_type(words, dtype)
            scale = 4 if view.ndim > 1 else 1
            views[dtype] = jax.lax.split(view.reshape(-1), [scale * n for n in sizes])
        return views[dtype]

    out = []
    for a, k in zip(like, index):
        if a.dtype.itemsize == 1:
            part = jax.lax.convert_element_type(stretches(jnp.uint8)[k][:a.size], a.dtype)
        else:
            part = stretches(a.dtype)[k]
        out.append(part if part.shape == tuple(a.shape) else jax.lax.reshape(part, tuple(a.shape)))
    return out


def words_of(a: Any) -> int:
    """The words array `a` (JAX, numpy, or a `jax.ShapeDtypeStruct`) takes in a flat array of words
    (`inbox_words`); other widths are refused by dtype."""
    count = inbox_words(a.size, a.dtype.itemsize)
    if count is None:
        raise ValueError(f"a lane exchanges arrays of 32-bit or 1-byte scalars, not {a.dtype} {a.shape}")
    return count


def _as_words(a: Any) -> Any:
    """JAX array `a` (32-bit or 1-byte elements) as flat float32 words with its bits kept, 1-byte elements four to
    a word in memory order, the last word's spare bytes zero."""
    import jax
    import jax.numpy as jnp

    if a.dtype.itemsize == 4:
        return jax.lax.bitcast_convert_type(a, jnp.float32).reshape(-1)
    flat = a.reshape(-1).astype(jnp.uint8)  # bool as 0/1, int8 as its two's-complement byte
    flat = jnp.pad(flat, (0, -flat.size % 4))
    return jax.lax.bitcast_convert_type(flat.reshape(-1, 4), jnp.float32)


class StreamEngine:
    """Buckets stepped concurrently, one CUDA stream and graph each (see the module docstring).

    `controls[k]` is a sequence of control batches [size_k, nu] for bucket k; `tick(j)` advances every bucket by
    one control step with its j-th batch (mod their number), without waiting; `synchronize()` waits. `serial=True`
    launches every graph on one stream: the same work in the order `Engine` runs it, for comparison. On Warp's CPU
    device a tick runs the buckets' steps in turn and returns when they are done.
    """

    def __init__(self, buckets: Sequence[Bucket], sizes: Sequence[int], controls: Sequence[Sequence[np.ndarray]],
                 serial: bool = False, device: str | None = None,
                 exchange: Sequence[dict[str, tuple[int, np.dtype]]] | None = None) -> None:
        """`device`: Warp's device for the lanes (None: Warp's default, the GPU where there is one). `exchange`
        (`StreamPhysics`), per bucket {MJX data leaf name: (its words, its element type)}: each lane loads every
        field of `exchange_fields` from its inbox, steps, puts back the state of the worlds that do not step and
        refreshes, all inside its graph, on data whose fields behind those leaves (`lane_array`) live in its outbox
        (`_house`), so that a tick moves one buffer each way per bucket; `controls` is then unused."""
        import warp as wp
        from mujoco.mjx.third_party import mujoco_warp as mjw

        from dojo.backends.mjx.cache import quiet_warp

        quiet_warp()
        wp.init()
        self.wp, self.mjw = wp, mjw
        self.device = wp.get_device(device)
        with wp.ScopedDevice(self.device):
            self._build(buckets, sizes, controls, serial, exchange)

    def _build(self, buckets: Sequence[Bucket], sizes: Sequence[int], controls: Sequence[Sequence[np.ndarray]],
               serial: bool, exchange: Sequence[dict[str, tuple[int, np.dtype]]] | None) -> None:
        """One lane per bucket on the current Warp device (see the class docstring)."""
        wp, mjw = self.wp, self.mjw
        self.on_gpu = self.device.is_cuda
        self.unbatched: dict[str, tuple[str, ...]] = {}
        shared = wp.Stream() if serial and self.on_gpu else None
        self.lanes: list[_Lane] = []
        for k, (bucket, size, ctrls) in enumerate(zip(buckets, sizes, controls)):
            ok, skipped = batchable_fields(bucket.varying)
            if skipped:
                self.unbatched[bucket.key] = skipped
            model = mjw.put_model(bucket.model, batch_sizes={name: size for name in ok})
            # MuJoCo Warp raises the solver's tolerance to 1e-6 for float32 (fewer iterations); MJX, so `Engine`,
            # keeps the plan's own (1e-8 by default): the same physics needs the same tolerance
            model.opt.tolerance.fill_(float(bucket.model.opt.tolerance))
            for name in ok:
                getattr(model, name).assign(world_values(bucket, size, name))
            contacts, rows = contact_capacity(bucket)
            data = mjw.make_data(bucket.model, nworld=size, naconmax=contacts * size, njmax=rows)
            member = np.arange(size) % len(bucket.members)
            data.qpos.assign(np.stack([bucket.members[i].qpos for i in member]).astype(np.float32))
            data.qvel.assign(np.stack([bucket.members[i].qvel for i in member]).astype(np.float32))
            xpos, xmat = bucket.geom_poses()  # fixtures' poses: Warp computes them in make_data only (`Bucket.table`)
            data.geom_xpos.assign(xpos[member].astype(np.float32))
            data.geom_xmat.assign(xmat[member].astype(np.float32))
            lane = _Lane(bucket, size, model, data, stream=None, graphs=[], programs=[], sources=[], batched=ok)
            if exchange is not None:
                self._exchanging(lane, exchange[k])
            else:
                lane.sources = [wp.array(np.asarray(c, np.float32), dtype=float) for c in ctrls]
                lane.programs = [_Program([(_words(wp, data.ctrl), _words(wp, src), 0, 0, src.size)])
                                 for src in lane.sources]
            if self.on_gpu:
                lane.stream = shared or wp.Stream()
                with wp.ScopedStream(lane.stream):
                    if lane.sources:
                        wp.copy(data.ctrl, lane.sources[0])
                    if not capture_loads_modules(wp):
                        _load_kernels(wp, mjw, model, data, lane.programs[0])
                    lane.graphs = [_capture(wp, mjw, lane.stream, model, data, program, bucket.n_substeps)
                                   for program in lane.programs]
            self.lanes.append(lane)
        self.lane_ticks = 0
        """Lane ticks launched by `tick`."""
        self.idle_ticks = 0
        """Lane ticks not launched because no environment of the lane reset or stepped (`tick`'s `active`)."""
        self._flags_at, total = word_offsets([lane.size for lane in self.lanes])
        self._flags = wp.zeros(total, dtype=int)
        """Every lane's per-world overflow bits side by side (`overflows`), lane k's from `_flags_at[k]`."""
        self.synchronize()

    def _exchanging(self, lane: _Lane, leaves: dict[str, tuple[int, np.dtype]]) -> None:
        """`lane`'s inbox, outbox and program under `exchange`: `leaves` are the MJX data leaves of 32-bit elements
        (name: (words, element type)) the tick keeps; the outbox houses every one the lane has (`lane.returned`,
        `_house`), and one it has in another layout or element type is refused by name. The element type is the
        engine's guarantee that the halves read the lane's words as the numbers the lane wrote: under `streams`
        the engine types its data as `make_data` made it, not as a tick returns it."""
        wp = self.wp
        arrays = {name: lane_array(wp, lane.data, name) for name in leaves}
        differ = [name for name, array in arrays.items()
                  if array is not None and _word_count(wp, array) != leaves[name][0]]
        if differ:  # a leaf the lane cannot return would stay at its first value in the engine's data
            raise ValueError(f"bucket {lane.bucket.key}: MJX's data and MuJoCo Warp's differ in layout for "
                             f"{differ}; a lane cannot return them")
        kinds = {name: (np.dtype(leaves[name][1]), np.dtype(wp.dtype_to_numpy(_scalar_type(array))))
                 for name, array in arrays.items() if array is not None}
        retyped = [f"{name} ({mjx} in MJX, {warp} in Warp)" for name, (mjx, warp) in kinds.items() if mjx != warp]
        if retyped:  # the halves would read the lane's bits as numbers of another kind
            raise ValueError(f"bucket {lane.bucket.key}: MJX's data and MuJoCo Warp's differ in element type for "
                             f"{', '.join(retyped)}; a lane cannot return them")
        lane.returned = tuple(name for name, array in arrays.items() if array is not None)
        lane.outbox = _house(wp, lane.data, lane.returned)  # first: the copies in below write the housed fields
        lane.stepping = wp.zeros(lane.size, dtype=wp.int32)
        owners = {"model": lane.model, "data": lane.data}
        loaded = [lane.stepping if owner == "lane" else getattr(owners[owner], name)
                  for owner, name in exchange_fields(lane.batched)]
        lane.inbox, loads = _inbox(wp, loaded)
        restores = []  # each state field from its words in the inbox, as loaded before the sub-steps
        fields = [field for field, array in zip(exchange_fields(lane.batched), loaded) if array.size]
        for (owner, name), (words, inbox, _, at, count) in zip(fields, loads):
            if owner == "data" and name in STATE_FIELDS:
                restores.append((lane.stepping, count // lane.size, words, _view(wp, inbox, at, wp.float32, (count,))))
        lane.programs = [_Program(loads, restores)]

    def tick(self, j: int = 0, active: Sequence[bool] | None = None) -> None:
        """Launch one control step of every bucket (its j-th control batch), or with `active` only of the buckets
        it marks (`lane_ticks` and `idle_ticks` count both); returns before the GPU finishes."""
        for lane, launched in zip(self.lanes, active if active is not None else [True] * len(self.lanes)):
            if launched:
                self._launch(lane, j)
                self.lane_ticks += 1
            else:
                self.idle_ticks += 1

    def _launch(self, lane: _Lane, j: int) -> None:
        """One control step of `lane` with its j-th control batch: its graph launched on its stream, or on Warp's
        CPU device its step run."""
        if lane.graphs:
            self.wp.capture_launch(lane.graphs[j % len(lane.graphs)], stream=lane.stream)
        else:
            self._step_eagerly(lane, j)

    def _step_eagerly(self, lane: _Lane, j: int) -> None:
        """`lane`'s control step with its j-th control batch, launch by launch (no graph) on the current stream."""
        with self.wp.ScopedDevice(self.device):
            _control_step(self.wp, self.mjw, lane.model, lane.data, lane.programs[j % len(lane.programs)],
                          lane.bucket.n_substeps)

    def lane_ms(self, ticks: int = 5) -> list[dict[str, Any]]:
        """Each lane's tick on its own, the others idle: its tasks, environments and median milliseconds over
        `ticks` launches, each waited for.

        Why: whether a concurrent tick is as long as its slowest lane (then splitting or shrinking that bucket is
        the lever) or as the lanes' sum over their overlap (then fewer graph nodes are). Under `StreamPhysics`, after
        a tick, a lane recomputes the tick its inbox still holds, so the next tick starts from the state it would
        have started from; what a lane keeps that its inbox does not reload (overflow bits, and in scenes that have
        them actuator delays and sleeping bodies) goes on with the extra ticks. Without `exchange` the extra ticks
        step the physics on."""
        import time

        out = []
        for lane in self.lanes:
            times = []
            for _ in range(ticks):
                start = time.perf_counter()
                self._launch(lane, 0)
                self.synchronize()
                times.append(time.perf_counter() - start)
            out.append({"tasks": list(lane.bucket.tasks), "envs": lane.size, "ms": 1e3 * float(np.median(times))})
        return out

    def kernel_ms(self, top: int = 12) -> list[dict[str, Any]]:
        """Per lane, one tick run launch by launch with each kernel timed on the GPU (`kernel_timing`): its tasks,
        environments, total GPU ms and launches, and the `top` kernels by time. What the extra tick leaves is as
        `lane_ms` says. Needs CUDA: Warp times kernels with CUDA events, and on its CPU device records nothing."""
        if not self.on_gpu:
            raise RuntimeError("kernel timing needs the lanes on a CUDA device: Warp times kernels with CUDA events")
        from dojo.backends.mjx.kernel_timing import kernel_table

        wp = self.wp
        out = []
        for lane in self.lanes:
            with wp.ScopedStream(lane.stream):
                wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
                self._step_eagerly(lane, 0)
                results = wp.timing_end()
            out.append({"tasks": list(lane.bucket.tasks), "envs": lane.size, **kernel_table(results, top)})
        return out

    def synchronize(self) -> None:
        """Wait for every stream (ticks return as soon as the graphs are launched)."""
        self.wp.synchronize_device()

    def overflows(self) -> dict[str, dict[str, int]]:
        """{bucket key: {what overflowed: worlds}}, as `Engine.overflows`, once the lanes are done: each lane's
        bits copied on the device into one array, which is read once. Why: the backend checks after every tick,
        and read lane by lane (a host copy and a wait each) the 141 lanes of the protocol's suite took about a
        tenth of its steady tick on an H200 (2026-12-03, stack samples: 3 of 31)."""
        wp = self.wp
        self.synchronize()
        for lane, at in zip(self.lanes, self._flags_at):
            wp.copy(self._flags, lane.data.overflow, dest_offset=at, count=lane.size)
        bits = self._flags.numpy()
        found = {lane.bucket.key: decode_overflow(bits[at:at + lane.size])
                 for lane, at in zip(self.lanes, self._flags_at)}
        return {k: v for k, v in found.items() if v}

    def check_overflow(self) -> None:
        """Raise `CapacityOverflow` if any bucket's buffers overflowed (figures of a lossy run are not reported)."""
        found = self.overflows()
        if found:
            raise CapacityOverflow(f"MuJoCo Warp dropped contacts or constraints: {found}")


def lane_figures(engine: Any, kernels: int) -> dict[str, Any]:
    """What `dojo bench sim` reports of an engine's lanes (a `StreamEngine`, or an `Engine` with `streams`): each
    lane alone (`lane_ms`) and, with `kernels` > 0, its `kernels` costliest kernels (`kernel_ms`); none for an
    engine without lanes. Their extra ticks count in the overflow check, which comes after."""
    figures = {"lane_ms": engine.lane_ms(), "kernel_ms": engine.kernel_ms(kernels) if kernels > 0 else []}
    return {name: value for name, value in figures.items() if value}


def measure_streams(buckets: Sequence[Bucket], sizes: Sequence[int], controls: Sequence[Sequence[np.ndarray]],
                    steps: int, warmup: int, serial: bool = True, kernels: int = 0) -> dict[str, Any]:
    """`dojo bench sim`'s `streams` figures: the buckets concurrently (one stream each), each lane alone
    (`lane_ms`; with `kernels` > 0 also its `kernels` costliest kernels, `kernel_ms`), then (with `serial`) the
    same graphs serially on one stream, each after `warmup` untimed ticks; overflow raises `CapacityOverflow`."""
    import time

    out: dict[str, Any] = {}
    envs = sum(sizes)
    substeps = sum(n * b.n_substeps for b, n in zip(buckets, sizes)) / envs
    runs = [("concurrent", False), ("serial", True)] if serial else [("concurrent", False)]
    for name, one_stream in runs:
        start = time.perf_counter()
        engine = StreamEngine(buckets, sizes, controls, serial=one_stream)
        setup = time.perf_counter() - start
        for k in range(warmup):
            engine.tick(k)
        engine.synchronize()
        start = time.perf_counter()
        for k in range(steps):
            engine.tick(k)
        engine.synchronize()
        seconds = time.perf_counter() - start
        lanes = {} if one_stream else lane_figures(engine, kernels)
        engine.check_overflow()  # the lanes' timing ticks included
        out[name] = {"interactions_per_s": envs * steps / seconds,
                     "physics_steps_per_s": envs * steps * substeps / seconds, "seconds": seconds, "setup_s": setup,
                     **lanes}
        if engine.unbatched:
            out["unbatched_fields"] = {k: list(v) for k, v in engine.unbatched.items()}
        log.info("streams (%s): %d bucket(s), %d envs, %.0f physics steps/s (set-up %.1f s)", name, len(buckets),
                 envs, out[name]["physics_steps_per_s"], setup)
        del engine
    if serial:
        out["concurrent_over_serial"] = out["concurrent"]["interactions_per_s"] / out["serial"]["interactions_per_s"]
    out.update(out.pop("concurrent"))
    return out


class StreamPhysics:
    """`Engine`'s physics on a `StreamEngine` (`backend.streams`): every bucket's sub-steps on its own CUDA stream.

    Why. Inside one jitted program XLA runs the buckets' Warp calls one after another, even when each is put on
    a stream of its own (README: XLA scheduled every call's end right after its start), while `StreamEngine`
    overlaps them (3.7x the same graphs on one stream: the 24-task mix at 4,096 environments, H200). So a tick
    becomes: a jitted half that resets, acts and writes the controls (`batch._before_physics`) and packs what each
    lane loads into one flat array (`pack_words`); this, which copies that array into the lane's inbox and launches
    the lanes' graphs (each moves its inbox into the fields, steps, puts back the state of the environments that
    do not step and refreshes what the observations read, on data that lives in its outbox); and a jitted half
    that reads the outboxes (one DLPack view each), observes, and copies them out as the engine's data
    (`Engine._words`). The host waits for the first half before it launches the lanes, and for the lanes before
    the second half, so each side reads only finished buffers.

    Why the refresh runs in the lanes: as a jitted call's `Hooks.refresh` (a forward) it was one MJX Warp call per
    bucket, each a Python callback on the host (2.3-2.9 ms each on an H200 host, 2026-12-02: the second half cost
    72 ms of a 208 ms tick at 29 buckets); inside the lane's graph it is a few more kernels (`refresh`).
    """

    def __init__(self, buckets: Sequence[Bucket], sizes: Sequence[int],
                 leaves: Sequence[dict[str, tuple[int, np.dtype]]]) -> None:
        """The lanes on the device JAX computes on (Warp's CPU device where JAX runs on the CPU, even on a host
        with a GPU), so that the halves and the lanes exchange buffers of one device. `leaves`, per bucket: the
        MJX data leaves the tick keeps, name: (words, element type) (`StreamEngine`'s `exchange`)."""
        import jax

        device = "cpu" if jax.default_backend() == "cpu" else None
        self.engine = StreamEngine(buckets, sizes, [[] for _ in buckets], device=device, exchange=leaves)
        self.batched = [lane.batched for lane in self.engine.lanes]
        """Per bucket, the varying model fields its lane loads each tick (`exchange_fields`)."""
        self.returned = [lane.returned for lane in self.engine.lanes]
        """Per bucket, the data leaves its outbox holds, in order."""
        self._views: list[Any] = []
        """The JAX inboxes the lanes copy from, as Warp arrays, kept alive from `launch` until `finish`."""

    def launch(self, inboxes: Sequence[Any], active: Sequence[bool] | None = None) -> None:
        """Start one control step of every bucket from `inboxes[k]`, the flat words of its `exchange_fields`
        (`pack_words`, a JAX array): the lanes run on their streams until `finish`, so that the lanes of several
        engines (`batch.EngineGroups`) run at once. With `active`, a bucket it marks False (none of its environments
        resets or steps this tick) is not launched at all, and its outbox keeps the words of its last tick.

        Why one buffer each way: loading a dozen fields per bucket through their own DLPack views cost about
        16 ms a tick at six buckets on an H200 host (2026-12-02, a `jax.profiler` trace); the fields now move
        between the buffer and the lane inside its graph.

        Why idle lanes are left out: a lane steps every world it holds, stepping or not, and puts the idle ones
        back afterwards, so a bucket whose episodes have all ended cost a whole tick until the run's end. In the
        protocol's default run on an H200 (2026-12-03, 850 episodes on mjx in 46 merged buckets) the tick stayed as
        long while its episodes ended: 3,300 interactions/s with all 850 stepping, 750 with 200 left. What a
        skipped lane leaves is what the jitted tick leaves for environments that do not step: every field as it
        was (a launched lane puts back their state and recomputes the rest from it)."""
        from contextlib import nullcontext

        wp = self.engine.wp
        active = list(active) if active is not None else [True] * len(self.engine.lanes)
        self._views = []  # what the copies read, alive until the lanes are done with them
        for lane, words, launched in zip(self.engine.lanes, inboxes, active):
            if words.shape != (lane.inbox.size,):
                raise ValueError(f"bucket {lane.bucket.key}: {words.shape[0]} words given for an inbox of "
                                 f"{lane.inbox.size}")
            if not launched:
                continue
            with wp.ScopedStream(lane.stream) if lane.stream is not None else nullcontext():
                self._views.append(wp.from_jax(words))
                wp.copy(lane.inbox, self._views[-1])
        self.engine.tick(0, active)

    def finish(self) -> list[Any]:
        """Wait for the lanes `launch` started and return each bucket's `returned` leaves after the step and a
        refresh as flat words (`unpack_words`), JAX arrays that view the lanes' outboxes (valid until the next
        launch)."""
        self.engine.synchronize()
        self._views = []
        return [self.engine.wp.to_jax(lane.outbox) for lane in self.engine.lanes]
