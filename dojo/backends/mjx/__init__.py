"""The batched MJX backend: heterogeneous parallelism over buckets of structurally identical models.

- `pad`: one task's plans rewritten to share one structure (clutter slots parked, lights/textures/names canonical);
- `bucket`: the structural signature MJX compiles against, buckets and their per-member varying model fields;
- `merge_groups`: which tasks of one robot share a merged bucket (only where the merged model stays small);
- `lanes`: a bucket's predicate programs, one per task when buckets are merged across tasks, picked per env;
- `batch`: `Engine`, every bucket's batch stepped in one jitted tick (sub-steps, resets, refills, hooks);
- `backend`: `MjxBackend`, the `Backend` interface with actions, predicates and proprioception on the device;
- `parity`: `parity_report` / `format_table`, agreement with the `mujoco` backend;
- `cache`: the persistent compilation cache and the choice of MJX implementation (`jax` or `warp`);
- `features`: which of a plan's `requires` this backend cannot run, and why;
- `sharding`: `Placement`, every bucket's batch split over the local devices (one process, several GPUs);
- `streams`: `StreamEngine`, each bucket's MuJoCo Warp physics on its own CUDA stream (`dojo bench sim` mode),
  and `StreamPhysics`, the same for `Engine`'s ticks (`backend.streams`);
- `lane_kernels`: the Warp kernels a lane's graph runs besides MuJoCo Warp's (the unstepped environments' state
  put back).
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from dojo.backends.registry import BackendOptions
    from dojo.backends.mjx.backend import MjxBackend

# MJX prints "Failed to import warp: ..." to stdout when MuJoCo Warp is absent (every CPU-only machine), which
# would break the one JSON line `dojo bench` prints; the message goes to the log instead.
with contextlib.redirect_stdout(io.StringIO()) as _printed:
    from mujoco import mjx as _mjx  # noqa: F401
if _printed.getvalue().strip():
    logging.getLogger(__name__).debug("mujoco.mjx: %s", _printed.getvalue().strip())

STREAMS_JAX_MEMORY = "0.5"
"""JAX's share of the GPU (`XLA_PYTHON_CLIENT_MEM_FRACTION`, read when JAX starts on it) with `backend.streams`,
whose lanes hold a second copy of every bucket's data through Warp's allocator."""

STREAMS_ENVIRONMENT = {"CUDA_DEVICE_MAX_CONNECTIONS": "32"}
"""Set, unless the user set them, wherever buckets run on their own CUDA streams, before the process first uses CUDA
(the driver reads it then). The driver feeds every stream of a device through 8 hardware queues by default (32 at
most); streams that share a queue wait on each other's kernels in order, so the protocol's 222 lanes overlapped only
4.5 deep. Measured on one H200 (2026-12-02, Warp kernels cached, `dojo bench sim backend.impl=warp num_envs=1200
plans=DIR episodes=null modes=[streams] steps=10 warmup=2` on `dojo compile suite=robodojo_sim seeds=[0]`'s 1,150
plans): 31.1k physics steps/s with 8 queues, 76.5k with 32 (2.46x). The mix of 29 buckets at 16,384 environments
ran the same either way (1.49M, 2026-11-28): there the kernels, not the queues, fill the GPU."""

ENGINE_STREAMS_ENVIRONMENT = {"XLA_PYTHON_CLIENT_MEM_FRACTION": STREAMS_JAX_MEMORY, **STREAMS_ENVIRONMENT}
"""What a process whose jitted engine runs its physics on streams (`backend.streams`) starts with, unless set:
JAX half the GPU beside the lanes, and every hardware queue."""

RUNS_POLICY_RULES = True
"""`MjxBackend.attach_rule`: a policy's joint-mode rule runs inside the tick (`dojo.backends.registry`)."""


def make(options: BackendOptions) -> MjxBackend:
    """The registry's constructor (`dojo.backends.registry`): settings `impl` (`jax`, `warp`, or auto), `devices`
    (how many local devices the environments are split over, or `all`), `merge` (buckets merged across tasks:
    true, false or auto, null: auto; `merge_groups.choose_merge`), `merge_growth` (how much larger than its largest
    plan a padded or merged model may be; null: `merge_groups.GROWTH`, or `AUTO_GROWTH` where auto merges),
    `graph_mode` (MJX's CUDA graph capture of Warp calls, `cache.GRAPH_MODES`; null:
    MJX's own default), `streams` (true, false or auto, null: auto; each bucket's physics on its own CUDA stream,
    under auto where `streams_may_run` and then `cache.choose_streams` allow) and
    `program_buckets` (at most this many buckets in one jitted program; null: `batch.PROGRAM_BUCKETS`).
    Every plan of the run is loaded up front (`preload`), so the run compiles once, and only for the action modes
    the policy sends (`options.action_modes`)."""
    check(options.settings)
    streams = options.settings.get("streams", "auto")
    streams = "auto" if streams is None else streams
    if streams == "auto" and not streams_may_run(options.settings.get("impl"), options.cameras):
        streams = False
    if streams:  # the lanes allocate through Warp: JAX takes half the GPU, not 3/4
        for name, value in ENGINE_STREAMS_ENVIRONMENT.items():
            os.environ.setdefault(name, value)
    import jax

    from dojo.compiler.plan import Plan

    from dojo.backends.mjx.backend import MjxBackend

    impl = options.settings.get("impl")
    merge, growth = merge_settings(options.settings)
    if jax.default_backend() == "cpu":
        logging.getLogger(__name__).warning(
            "backend=mjx on a CPU: %s; backend=mujoco is the CPU backend",
            "MuJoCo Warp on Warp's CPU device, for checks: a second or more per step" if str(impl) == "warp" else
            "expect minutes of compilation and seconds per step (every contact candidate is simulated)")
    backend = MjxBackend(impl=str(impl) if impl is not None else None, privileged=options.privileged,
                         plan_paths=dict(options.plan_paths or {}), cameras=options.cameras, width=options.width,
                         height=options.height, depth=options.depth, devices=options.settings.get("devices"),
                         merge=merge, merge_growth=growth,
                         graph_mode=options.settings.get("graph_mode"), action_modes=options.action_modes,
                         streams=streams,
                         program_buckets=options.settings.get("program_buckets"))
    backend.preload([Plan.load(Path(p)) for p in (options.plan_paths or {}).values()])
    return backend


def check(settings: Mapping[str, Any]) -> None:
    """Refuse, by name, a `backend.streams` or `backend.merge` other than true, false or auto (null: auto), and a
    `backend.merge_growth` that is not a number of at least 0 (`registry.check_settings`: before a run starts)."""
    streams = settings.get("streams")
    if streams not in (None, True, False, "auto"):
        raise ValueError(f"backend.streams takes true, false or auto, not {streams!r}")
    merge_settings(settings)


def merge_settings(settings: Mapping[str, Any]) -> tuple[bool | str, float | None]:
    """`backend.merge` and `backend.merge_growth` as the backend and `dojo bench kernels` take them: the merge true,
    false or `auto` (null: auto), the growth a float or None (unset); either refused by name where it is not one of
    those (`merge_groups.choose_merge` decides what they mean for a run)."""
    from dojo.backends.mjx.merge_groups import choose_merge

    merge, given = settings.get("merge"), settings.get("merge_growth")
    merge = "auto" if merge is None else merge
    try:
        growth = None if given is None else float(given)
    except (TypeError, ValueError):
        growth = math.nan
    if growth is not None and not growth >= 0:
        raise ValueError(f"backend.merge_growth takes a number of at least 0 or null, not {given!r}")
    choose_merge(merge, growth, False, 0, 0)
    return merge, growth


def streams_may_run(impl: Any, cameras: Sequence[str]) -> bool:
    """Whether `backend.streams=auto` may put this process's physics on streams, decided before JAX or Warp start
    CUDA, since the environment they need (`ENGINE_STREAMS_ENVIRONMENT`) is read then: `impl` auto or warp with
    MuJoCo Warp installed, no cameras (cameras on streams are checked bit for bit on Warp's CPU device only, not
    yet on a GPU), and an NVIDIA device visible (`nvidia_devices`). The backend then decides (`choose_streams`).

    Why auto: at the protocol's scale (850 plans in 141 buckets, 1,200 environments, H200, 2026-12-02) the jitted
    tick stepped the buckets one after another at 259-293 interactions/s; on streams the same buckets' physics ran
    4.6x to 11x faster (`dojo bench sim`, README)."""
    from dojo.backends.mjx.cache import warp_installed

    return (str(impl) in ("None", "auto", "warp") and not cameras and nvidia_devices() > 0
            and warp_installed())


def nvidia_devices(dev: Path = Path("/dev"), environ: Mapping[str, str] = os.environ) -> int:
    """How many NVIDIA GPUs this process may see, without starting CUDA: the driver's device nodes
    (`/dev/nvidia0`, ...), as many as `CUDA_VISIBLE_DEVICES` lists when it is set (none when it is empty or -1)."""
    nodes = sum(1 for path in dev.glob("nvidia*") if path.name[len("nvidia"):].isdigit())
    visible = environ.get("CUDA_VISIBLE_DEVICES")
    if visible is None:
        return nodes
    listed = [d for d in visible.split(",") if d.strip()]
    return 0 if not listed or listed[0].strip() == "-1" else min(nodes, len(listed))


def merge_growth(setting: Any) -> float:
    """`backend.merge_growth` as a float: null (the default) is `merge_groups.GROWTH`; `.inf` merges every task a
    robot's scenes allow (one union, slower on the GPU)."""
    from dojo.backends.mjx.merge_groups import GROWTH

    return GROWTH if setting is None else float(setting)


def unsupported(features: Sequence[str], settings: Mapping[str, Any]) -> dict[str, str]:
    """The registry's question (`dojo.backends.registry.unsupported_features`), answered by `features`."""
    from dojo.backends.mjx.features import unsupported as answer

    return answer(features, settings)
