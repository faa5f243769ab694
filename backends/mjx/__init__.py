"""The batched MJX backend: heterogeneous parallelism over buckets of structurally identical models.

- `pad`: one task's plans rewritten to share one structure (clutter slots parked, lights/textures/names canonical);
- `bucket`: the structural signature MJX compiles against, buckets and their per-member varying model fields;
- `batch`: `Engine`, every bucket's batch stepped in one jitted tick (sub-steps, resets, refills, hooks);
- `backend`: `MjxBackend`, the `Backend` interface with actions, predicates and proprioception on the device;
- `parity`: `parity_report` / `format_table`, agreement with the `mujoco` backend;
- `cache`: the persistent compilation cache and the choice of MJX implementation (`jax` or `warp`).
"""
