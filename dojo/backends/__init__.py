"""Backends run plans: `mujoco` (the CPU reference, one MjData per environment) and `mjx` (batched on JAX)."""

from dojo.backends.gl_platform import choose_gl_platform

# Before any backend module imports `mujoco`, which reads MUJOCO_GL once: a script run as
# `python -m dojo.backends.<...>` imports this package first, and would otherwise get MuJoCo's default (GLFW, which
# fails headless with "gladLoadGL error"). The CLI has chosen already; a platform the user set is kept.
choose_gl_platform()
