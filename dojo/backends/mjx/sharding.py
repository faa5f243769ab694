"""Several devices in one process: every bucket's environments split over the local devices along the batch axis.

A bucket's environments are independent of each other, so the engine's batch axis is the natural one to split:
the tick's state, flags, inputs and outputs are sharded along it over a one-axis `Mesh` of the devices, while the
shared models and member tables are replicated on each. Each device runs the one-device tick on its own rows
(`shard_map`): the program each device runs is the one-device program of a smaller batch, with no collective a
partitioner might insert and no traffic between devices. One `dojo run backend=mjx` thereby uses every GPU of its
host, and the same code runs on one device.

A sharded axis must divide evenly, so a bucket's batch is padded up to a multiple of the device count, with at
least `MIN_SHARE` rows per device (`Placement.padded`); the backend leaves the padding rows without a slot, and they
never step. Bit-for-bit agreement has two limits, both XLA's on a CPU, measured on toy buckets: a batch axis of one
row is simplified away and rounds differently from the same row in a larger batch (on one device too), hence
MIN_SHARE; and Eigen's multi-threaded kernels split their sums by the threads each device gets, so with
`--xla_cpu_multi_thread_eigen=true` (the default) a split run differs from one device in the last float32 bits
(up to 1e-6 in velocities after a few steps); with it off the two agree bit for bit (tests/backends_mjx).

On a CPU the test suite forces several host devices (`XLA_FLAGS=--xla_force_host_platform_device_count=4`, set
before JAX starts), which exercises the same partitioning as several GPUs.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

log = logging.getLogger(__name__)
AXIS = "envs"
"""The mesh axis the environments are split along."""
MIN_SHARE = 2
"""Fewest rows of a bucket's batch each device holds when there are several (see the module docstring)."""


def local_devices(count: int | str | None = None) -> list[jax.Device]:
    """The first `count` local devices of JAX's default platform; all of them for None or 'all'."""
    devices = jax.local_devices()
    if count in (None, "", "all"):
        return devices
    try:
        n = int(count)
    except (TypeError, ValueError):
        raise ValueError(f"devices={count!r}: give a number of devices or 'all'") from None
    if not 1 <= n <= len(devices):
        raise ValueError(f"devices={n}: this process sees {len(devices)} {devices[0].platform} device(s)")
    return devices[:n]


@dataclass(frozen=True)
class Placement:
    """Where the engine's arrays live: batched ones split along `AXIS` over `mesh`, the others replicated."""

    mesh: Mesh

    @classmethod
    def over(cls, devices: Sequence[jax.Device] | None, impl: str) -> "Placement":
        """A placement over `devices` (all local ones when None). MuJoCo Warp's kernels are foreign calls XLA
        cannot partition, so the `warp` implementation keeps to the first device."""
        devices = list(devices) if devices is not None else local_devices()
        if impl == "warp" and len(devices) > 1:
            log.warning("mjx impl=warp runs on one device (%s): XLA cannot split MuJoCo Warp's kernels over %d",
                        devices[0], len(devices))
            devices = devices[:1]
        return cls(Mesh(np.asarray(devices), (AXIS,)))

    @property
    def count(self) -> int:
        """How many devices the batches are split over."""
        return int(self.mesh.devices.size)

    @property
    def batched(self) -> NamedSharding:
        return NamedSharding(self.mesh, PartitionSpec(AXIS))

    @property
    def replicated(self) -> NamedSharding:
        return NamedSharding(self.mesh, PartitionSpec())

    def padded(self, size: int) -> int:
        """`size` rounded up to a multiple of the device count, at least MIN_SHARE rows per device (one device:
        `size`, at least 1)."""
        share = -(-size // self.count)
        return max(share, MIN_SHARE if self.count > 1 else 1) * self.count

    def check(self, sizes: Sequence[int]) -> None:
        """Every batch must split evenly over the devices; say how to pad one that does not."""
        uneven = [n for n in sizes if n % self.count]
        if uneven:
            raise ValueError(f"batch sizes {uneven} do not split over {self.count} devices: pad each with "
                             f"Placement.padded (e.g. {uneven[0]} -> {self.padded(uneven[0])})")

    def per_device(self, fn: Callable[..., Any], replicated: int, batched: int) -> Callable[..., Any]:
        """`fn` of `replicated` then `batched` arguments, run by each device on its rows of the batched ones
        (outputs batched); `fn` itself on one device. Jit it with `in_shardings(...)` and `out_shardings=batched`."""
        if self.count == 1:
            return fn
        specs = (PartitionSpec(),) * replicated + (PartitionSpec(AXIS),) * batched
        return jax.shard_map(fn, mesh=self.mesh, in_specs=specs, out_specs=PartitionSpec(AXIS), check_vma=False)

    def in_shardings(self, replicated: int, batched: int) -> tuple[NamedSharding, ...]:
        return (self.replicated,) * replicated + (self.batched,) * batched

    def put_batched(self, tree: Any) -> Any:
        return jax.device_put(tree, self.batched)

    def put_replicated(self, tree: Any) -> Any:
        return jax.device_put(tree, self.replicated)

    @property
    def on_gpu(self) -> bool:
        """Whether the batches live on GPUs (`backend.streams=auto` runs streams only there)."""
        return self.mesh.devices.reshape(-1)[0].platform == "gpu"

    def describe(self) -> str:
        devices = self.mesh.devices.reshape(-1)
        return f"{self.count} {devices[0].platform} device(s): {', '.join(str(d) for d in devices)}"
