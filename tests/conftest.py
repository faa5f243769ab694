"""Test-wide set-up: headless rendering.

MuJoCo chooses its OpenGL platform when it is first imported, and test modules import it at collection time, so
the choice is made here, before any of them: EGL (Mesa's software driver where there is no GPU), as the CLI does.
"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
