"""xpolicylab imports with only numpy, msgpack and websockets: never mujoco, jax, the simulator or Hydra."""

from __future__ import annotations

import subprocess
import sys

SCRIPT = r"""
import importlib, pkgutil, sys
for banned in ("mujoco", "mujoco_mjx", "jax", "jaxlib", "dojo", "yaml", "hydra", "omegaconf", "msgpack_numpy",
               "openpi_client", "torch"):
    sys.modules[banned] = None  # any import of these now raises ImportError
import xpolicylab
names = [m.name for m in pkgutil.walk_packages(xpolicylab.__path__, "xpolicylab.")]
for name in names:
    importlib.import_module(name)
print(len(names))
"""


def test_every_module_imports_without_heavy_dependencies():
    result = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert int(result.stdout) >= 14  # every module was imported
