"""Camera images of the mjx backend rendered on the GPU, from the simulation state where it already is.

Under `impl='warp'` each bucket gets a `WarpRenderer` (MuJoCo Warp's batched ray tracer) sized to its rows. After
a tick, `BucketCameras.frames` renders every row of the bucket in one jitted call, from the engine's own batched
`mjx.Data` and the members' per-environment model fields (colours, lights, textures of the random setting) gathered
from the bucket's member table, exactly as the physics sees them; only the rows asked for leave the device, on a GPU
into kept page-locked buffers (`host_copy`), lent by the policy link where it has shared memory
(`use_buffers`). They leave camera by camera: each camera's images of every row lie one after another on the host,
so that a policy link sends one camera's batch as one array where it lies (`xpolicylab.columns.Rows.runs`); the
frames handed back are views in the usual `[rows, cameras, ...]` order. The host renderer
(`render.CpuRenderer`) remains the path under `jax`: it re-renders each environment from its qpos with MuJoCo's
OpenGL renderer.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dojo.backends.base import HostBuffers
from dojo.backends.mjx.batch import BucketArrays
from dojo.backends.mjx.capture import run_settled
from dojo.backends.mjx.host_copy import PinnedCopier
from dojo.backends.mjx.render import Frames, RenderConfig, WarpRenderer


class BucketCameras:
    """The observed cameras of one bucket's `nworld` rows, rendered on the device (see the module docstring)."""

    def __init__(self, arrays: BucketArrays, config: RenderConfig, buffers: HostBuffers | None = None) -> None:
        self.arrays = arrays
        self.renderer = WarpRenderer(arrays.bucket.model, arrays.size, config)
        varying, in_axes = tuple(arrays.bucket.varying), arrays.in_axes
        # the model and table as leaves taken once: MJX's model flattens in Python per call (`Engine._flat`)
        self._model, model_def = jax.tree.flatten((arrays.mx, arrays.table))

        def render(model: list, member: jax.Array, data: Any) -> Frames:
            mx, table = jax.tree.unflatten(model_def, model)
            return self.renderer(mx.tree_replace({name: table[name][member] for name in varying}), data, in_axes)

        self._render = jax.jit(render)
        # The rows asked for, camera-major ([cameras, rows, ...]). Apart from the render, which serves every call
        # as one program (its Warp calls capture CUDA graphs), since how many rows are asked for varies.
        self._pick = jax.jit(lambda images, rows: jnp.swapaxes(images[rows], 0, 1))
        self._copier = PinnedCopier(buffers=buffers)

    def use_buffers(self, buffers: HostBuffers | None) -> None:
        """Take host buffers for images from `buffers` from now on (`MjxBackend.use_image_buffers`)."""
        self._copier.buffers = buffers

    def close(self) -> None:
        """Let go of the kept host buffers (lent ones given back)."""
        self._copier.close()

    def frames(self, data: Any, members: np.ndarray, rows: Sequence[int]) -> Frames:
        """Images of `rows` of the bucket at the engine's current state `data` (`members`: every row's member
        index), only those rows copied to the host. Run settled: the renderer's Warp calls capture CUDA graphs on
        first use."""
        out = run_settled(self._render, self._model, jnp.asarray(members, jnp.int32), data)
        pick = jnp.asarray(np.asarray(rows, np.int32))

        def host(images: jax.Array) -> np.ndarray:
            return np.swapaxes(self._copier.to_host(self._pick(images, pick)), 0, 1)

        return Frames(host(out.rgb), None if out.depth is None else host(out.depth))
