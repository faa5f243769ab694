"""`xpolicylab new` writes a package whose scripts share deploy.yml and whose eval.sh passes the checker."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from xpolicylab.params import apply_overrides, experiment_params, load_params, shell_exports
from xpolicylab.policies import load_policy
from xpolicylab.template import FILES, new_policy

from conftest import free_port


def _run(script: Path, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHON=sys.executable)
    return subprocess.run(["bash", str(script), *args], cwd=script.parent, env=env, capture_output=True, text=True,
                          timeout=120)


def test_generated_package_has_every_file_and_shared_params(tmp_path):
    pkg = new_policy("my_policy", tmp_path, task="hang_mugs", seed=3)
    assert sorted(p.name for p in pkg.iterdir()) == sorted(FILES)
    params = experiment_params(pkg / "deploy.yml", [])
    assert {"dataset", "task", "checkpoint", "robot", "action_type", "seed"} <= params.keys()
    assert params["task"] == "hang_mugs" and params["seed"] == 3
    assert params["checkpoint"] == "checkpoints/hang_mugs/seed3"
    # the image size the policy declares is a parameter too, and the served metadata carries it
    overridden = experiment_params(pkg / "deploy.yml", ["image_width=160", "image_height=120"])
    declared = load_policy(str(pkg / "model.py"), overridden).metadata
    assert (params["image_width"], params["image_height"]) == (224, 224)
    assert (declared.image_width, declared.image_height) == (160, 120)
    for script in ("install.sh", "process_data.sh", "train.sh", "eval.sh"):
        assert os.access(pkg / script, os.X_OK)
        assert subprocess.run(["bash", "-n", str(pkg / script)]).returncode == 0


def test_eval_sh_passes_the_checker_as_generated(tmp_path):
    pkg = new_policy("fresh", tmp_path)
    result = _run(pkg / "eval.sh", f"port={free_port()}")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "RESULT: PASS" in result.stdout


def test_process_data_and_train_read_the_same_params(tmp_path):
    pkg = new_policy("trainee", tmp_path, task="push_T")
    processed = _run(pkg / "process_data.sh")
    assert processed.returncode == 0, processed.stderr
    assert (pkg / "data" / "push_T").is_dir() and "push_T" in processed.stdout
    trained = _run(pkg / "train.sh", "seed=2")
    assert trained.returncode == 0, trained.stderr
    assert (pkg / "checkpoints" / "push_T" / "seed2" / "checkpoint.json").is_file()


def test_refuses_bad_names_and_existing_folders(tmp_path):
    with pytest.raises(ValueError):
        new_policy("1bad-name", tmp_path)
    with pytest.raises(ValueError):
        new_policy("ok", tmp_path, robot="ur5")
    new_policy("taken", tmp_path)
    with pytest.raises(FileExistsError):
        new_policy("taken", tmp_path)


def test_params_overrides_and_exports(tmp_path):
    path = tmp_path / "deploy.yml"
    path.write_text("# comment\ntask: stack_bowls  # trailing\nseed: 0\nname: 'two words'\nflag: true\n")
    params = load_params(path)
    assert params == {"task": "stack_bowls", "seed": 0, "name": "two words", "flag": True}
    assert apply_overrides(params, ["seed=4"])["seed"] == 4
    with pytest.raises(ValueError, match="seed"):
        apply_overrides(params, ["sed=4"])
    assert "export NAME='two words'" in shell_exports(params)
    path.write_text("task: push_T\nseed: 0\ncheckpoint: ckpt/{task}/seed{seed}\n")
    assert experiment_params(path, ["seed=5"])["checkpoint"] == "ckpt/push_T/seed5"
