"""Backends run plans: `mujoco` (the CPU reference, one MjData per environment) and `mjx` (batched on JAX)."""
