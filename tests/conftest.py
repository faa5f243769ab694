"""Test-wide set-up: headless rendering, and ffmpeg started without Python code between fork and exec.

MuJoCo chooses its OpenGL platform when it is first imported, and test modules import it at collection time, so
the choice is made here, before any of them: EGL (Mesa's software driver where there is no GPU), as the CLI does.

Tests read the videos that runs record with imageio, whose ffmpeg reader is started with a `preexec_fn` unless
this variable is set (as `dojo.runtime.recorder.Mp4Writer` sets it for writing): in a test process where JAX's
threads already run, that is a fork of a multithreaded process running Python, which can deadlock.
"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ.setdefault("IMAGEIO_FFMPEG_NO_PREVENT_SIGINT", "1")
