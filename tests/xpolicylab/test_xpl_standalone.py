"""xpolicylab installs on its own (numpy, msgpack, websockets only) and works from that install."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

SOURCE = Path(__file__).resolve().parents[2] / "xpolicylab"

SCRIPT = r"""
import sys
for banned in ("mujoco", "mujoco_mjx", "jax", "jaxlib", "dojo", "yaml", "hydra", "omegaconf"):
    sys.modules[banned] = None
import xpolicylab
from xpolicylab.template import new_policy
from xpolicylab.server import ServerConfig, ServerThread
from xpolicylab.policies import load_policy
from xpolicylab.checker import CheckConfig, run_check
assert xpolicylab.__file__.startswith(sys.argv[1]), xpolicylab.__file__
pkg = new_policy("standalone", sys.argv[2])
config = {"policy_name": "standalone", "action_type": "joint", "chunk_size": 4, "checkpoint": "none",
          "robot": "arx_x5_bimanual", "image_width": 224, "image_height": 224}
with ServerThread(load_policy(str(pkg / "model.py"), config), ServerConfig(port=0)) as srv:
    report = run_check(CheckConfig(url=srv.url, n=2, width=224, height=224))
print(report.format())
sys.exit(0 if report.passed else 1)
"""


def test_standalone_wheel_has_light_dependencies_and_works(tmp_path):
    source = tmp_path / "src" / "xpolicylab"
    shutil.copytree(SOURCE, source, ignore=shutil.ignore_patterns("__pycache__", "build", "*.egg-info"))
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w",
                    str(wheels), str(source)], check=True, timeout=300)
    (wheel,) = wheels.glob("xpolicylab-*.whl")
    with zipfile.ZipFile(wheel) as zf:
        names = zf.namelist()
        metadata = zf.read(next(n for n in names if n.endswith("METADATA"))).decode()
    requires = sorted(line.split(":", 1)[1].strip().split(">")[0].split("=")[0].strip()
                      for line in metadata.splitlines() if line.startswith("Requires-Dist"))
    assert requires == ["msgpack", "numpy", "websockets"]
    assert "xpolicylab/templates/policy/model.py.tmpl" in names and "xpolicylab/pyproject.toml" not in names
    site = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(site), str(wheel)],
                   check=True, timeout=300)
    env = dict(os.environ, PYTHONPATH=str(site))
    result = subprocess.run([sys.executable, "-c", SCRIPT, str(site), str(tmp_path / "pkgs")], env=env,
                            cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "RESULT: PASS" in result.stdout
