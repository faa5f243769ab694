"""Which OpenGL platform MuJoCo's renderer uses, chosen before `mujoco` is first imported.

MuJoCo reads MUJOCO_GL once, at import, and with `egl` or `osmesa` PyOpenGL loads that library at import too: on
a machine without it (a GPU server whose driver ships `libEGL_nvidia` but no `libEGL.so.1` loader, say) a plain
`import mujoco` then fails with `'NoneType' object has no attribute 'eglQueryString'`, although physics needs no
OpenGL at all. So the platform is probed, not assumed: the first of EGL and OSMesa whose library loads, else
`disable` (physics, MJX and MuJoCo Warp's renderer work; MuJoCo's own renderer says why it cannot open).

A MUJOCO_GL the user set is always kept. The probe only loads the shared library (no context is created), so it
costs milliseconds and has no effect on a later import. This module imports nothing heavy: the CLI calls it first.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
from typing import Callable

LIBRARIES = {
    "egl": ("EGL", ("libEGL.so.1", "libEGL.so")),
    "osmesa": ("OSMesa", ("libOSMesa.so.8", "libOSMesa.so.6", "libOSMesa.so")),
}
"""Per headless platform: the name PyOpenGL looks up with `ctypes.util.find_library`, and the file names tried."""
HEADLESS = ("egl", "osmesa")
"""Headless platforms in order of preference: EGL renders on the GPU where there is one (Mesa's software driver
elsewhere); OSMesa is software only."""
DISABLED = "disable"
_REASON_VAR = "DOJO_GL_REASON"
"""Why the platform in MUJOCO_GL was chosen, kept in the environment so that child processes can say it too."""


def library_loads(platform: str) -> bool:
    """Whether the shared library of a headless platform (`egl` or `osmesa`) can be loaded here."""
    name, files = LIBRARIES[platform]
    found = ctypes.util.find_library(name)
    for candidate in ((found,) if found else ()) + files:
        try:
            ctypes.CDLL(candidate)
        except OSError:
            continue
        return True
    return False


def choose_gl_platform(loads: Callable[[str], bool] = library_loads) -> str:
    """Set MUJOCO_GL (and PyOpenGL's platform to match) unless the user set it, and return it.

    The first platform of HEADLESS whose library loads, else `disable`, with the reason kept in DOJO_GL_REASON
    (read by `gl_unavailable_reason`). `loads` is the probe (replaced in tests).
    """
    chosen = os.environ.get("MUJOCO_GL", "").strip().lower()
    if chosen:
        os.environ.setdefault(_REASON_VAR, f"MUJOCO_GL={chosen} was set by the user")
    else:
        chosen = next((p for p in HEADLESS if loads(p)), DISABLED)
        os.environ["MUJOCO_GL"] = chosen
        os.environ[_REASON_VAR] = (f"{chosen}: its library loads" if chosen != DISABLED else
                                   "neither libEGL.so.1 nor libOSMesa could be loaded")
    if chosen in HEADLESS:
        os.environ.setdefault("PYOPENGL_PLATFORM", chosen)
    return chosen


def gl_enabled() -> bool:
    """Whether MuJoCo's renderer can be used in this process (MUJOCO_GL is not a disabling value)."""
    return os.environ.get("MUJOCO_GL", "").strip().lower() not in ("disable", "disabled", "off", "false", "0")


def gl_unavailable_reason() -> str:
    """One line for users: why MuJoCo's renderer is off here and what to do about it."""
    why = os.environ.get(_REASON_VAR, f"MUJOCO_GL={os.environ.get('MUJOCO_GL', '')}")
    return (f"MuJoCo's OpenGL renderer is disabled on this machine ({why}); install an EGL loader (libegl1) or "
            "OSMesa (libosmesa6), or set MUJOCO_GL=egl|osmesa|glfw. Physics and the MJX/MuJoCo Warp renderer "
            "do not need it.")
