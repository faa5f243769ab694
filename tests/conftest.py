"""Test-wide set-up: headless rendering, ffmpeg started without Python code between fork and exec, and the longest
test file first.

MuJoCo chooses its OpenGL platform when it is first imported, and test modules import it at collection time, so
the choice is made here, before any of them, as the CLI makes it: EGL (Mesa's software driver where there is no
GPU), else OSMesa, else none (a GPU machine without libEGL runs the physics and Warp tests).

Tests read the videos that runs record with imageio, whose ffmpeg reader is started with a `preexec_fn` unless
this variable is set (as `dojo.evaluation.recorder.Mp4Writer` sets it for writing): in a test process where JAX's
threads already run, that is a fork of a multithreaded process running Python, which can deadlock.

With `-n 2 --dist loadfile` (CI), files go to whichever worker is free, in collection order. The README's quick
start (5-6 minutes, one file) came late in that order, and ran while the other worker had nothing left to do; run
first, it overlaps everything else.
"""

import os

from dojo.backends.gl_platform import choose_gl_platform

choose_gl_platform()
os.environ.setdefault("IMAGEIO_FFMPEG_NO_PREVENT_SIGINT", "1")

LONGEST_FIRST = "test_readme.py"


def pytest_collection_modifyitems(config, items):
    """The README's tests first (see the module docstring); the rest keep their order (a stable sort)."""
    items.sort(key=lambda item: item.path.name != LONGEST_FIRST)
