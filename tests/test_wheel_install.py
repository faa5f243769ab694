"""The built wheel works on its own: specs, schemas, assets and CLI config are shipped as package data.

The wheel is installed without dependencies into a separate folder that is put first on the path, and the test
checks that the modules really come from there (not from the editable checkout) before using them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel_site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    dist = tmp_path_factory.mktemp("dist")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(dist),
                    str(REPO)], check=True, capture_output=True, timeout=600)
    wheel = next(dist.glob("robodojo-*.whl"))
    site = tmp_path_factory.mktemp("site")
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(site), str(wheel)],
                   check=True, capture_output=True, timeout=600)
    return site


def run_installed(site: Path, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(site))
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, env=env, cwd=cwd, timeout=300)


def test_modules_come_from_the_wheel(wheel_site: Path, tmp_path: Path) -> None:
    code = ("import json, dojo.compiler, dojo.cli, dojo.specs, dojo.assets, xpolicylab;"
            "print(json.dumps([m.__file__ for m in (dojo.compiler, dojo.cli, dojo.specs, dojo.assets, xpolicylab)]))")
    result = run_installed(wheel_site, "-c", code, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    for path in json.loads(result.stdout):
        assert Path(path).is_relative_to(wheel_site), path


def test_installed_cli_validates_and_lists_the_builtin_specs(wheel_site: Path, tmp_path: Path) -> None:
    specs = wheel_site / "dojo" / "specs"
    assets = wheel_site / "dojo" / "assets"
    assert (specs / "schemas" / "task.schema.json").is_file()
    result = run_installed(wheel_site, "-m", "dojo.cli.main", "validate", str(specs), str(assets), cwd=tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "all valid" in result.stdout
    listed = run_installed(wheel_site, "-m", "dojo.cli.main", "list", "robots", "--format", "json", cwd=tmp_path)
    assert listed.returncode == 0, listed.stderr
    assert len(json.loads(listed.stdout)) >= 3
    config = run_installed(wheel_site, "-m", "dojo.cli.main", "show", "robot=arx_x5_bimanual", "--cfg", "job",
                           cwd=tmp_path)
    assert config.returncode == 0 and "id: arx_x5_bimanual" in config.stdout, config.stderr


def test_plan_hashes_match_the_checkout(wheel_site: Path, tmp_path: Path) -> None:
    """Hashes name paths relative to each package, so a wheel install compiles to the same plan names."""
    code = ("from dojo.compiler.spec_library import SpecLibrary; from dojo.compiler.plan import plan_hash;"
            "lib = SpecLibrary.load(); t = lib.get('task', 'classify_objects');"
            "print(plan_hash(lib, t, 'random', 4))")
    from_wheel = run_installed(wheel_site, "-c", code, cwd=tmp_path)
    assert from_wheel.returncode == 0, from_wheel.stderr
    from_checkout = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path,
                                   timeout=300)
    assert from_wheel.stdout.strip() == from_checkout.stdout.strip() != ""
