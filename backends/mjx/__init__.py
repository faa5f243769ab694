"""The batched MJX backend: heterogeneous parallelism over buckets of structurally identical models.

- `pad`: one task's plans rewritten to share one structure (clutter slots parked, lights/textures/names canonical);
- `bucket`: the structural signature MJX compiles against, buckets and their per-member varying model fields;
- `batch`: `Engine`, every bucket's batch stepped in one jitted tick (sub-steps, resets, refills, hooks);
- `backend`: `MjxBackend`, the `Backend` interface with actions, predicates and proprioception on the device;
- `parity`: `parity_report` / `format_table`, agreement with the `mujoco` backend;
- `cache`: the persistent compilation cache and the choice of MJX implementation (`jax` or `warp`).
"""

import contextlib
import io
import logging

# MJX prints "Failed to import warp: ..." to stdout when MuJoCo Warp is absent (every CPU-only machine), which
# would break the one JSON line `dojo bench` prints; the message goes to the log instead.
with contextlib.redirect_stdout(io.StringIO()) as _printed:
    from mujoco import mjx as _mjx  # noqa: F401
if _printed.getvalue().strip():
    logging.getLogger(__name__).debug("mujoco.mjx: %s", _printed.getvalue().strip())
