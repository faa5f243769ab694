"""``xpolicylab new NAME``: write a policy package that passes the checker as generated.

The package's scripts (install, process_data, train, eval) and its Python entry points (model.py, deploy.py)
all read one ``deploy.yml``, so dataset, task, checkpoint, robot, action type and seed are set in one place.
"""

from __future__ import annotations

import re
from importlib import resources
from pathlib import Path
from typing import Any

from xpolicylab.embodiments import ACTION_MODES, EMBODIMENTS

FILES = ("install.sh", "process_data.sh", "train.sh", "eval.sh", "model.py", "deploy.py", "deploy.yml")
DEFAULTS: dict[str, Any] = {"task": "my_task", "robot": "arx_x5_bimanual", "action_type": "joint",
                            "chunk_size": 8, "seed": 0}
_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")


def render(text: str, values: dict[str, Any]) -> str:
    """Fill ``{{key}}`` placeholders (braces that do not name a value are left alone)."""
    for key, value in values.items():
        text = text.replace("{{" + key + "}}", str(value))
    return text


def new_policy(name: str, directory: str | Path = ".", **params: Any) -> Path:
    """Create ``directory/name`` from the template and return its path."""
    if not _NAME.match(name):
        raise ValueError(f"policy name {name!r} must start with a letter and use only letters, digits and _")
    values = {**DEFAULTS, **params, "name": name}
    if values["robot"] not in EMBODIMENTS:
        raise ValueError(f"robot must be one of {sorted(EMBODIMENTS)}, got {values['robot']!r}")
    if values["action_type"] not in ACTION_MODES:
        raise ValueError(f"action_type must be one of {ACTION_MODES}, got {values['action_type']!r}")
    target = Path(directory) / name
    if target.exists() and any(target.iterdir()):
        raise FileExistsError(f"{target} already exists and is not empty")
    target.mkdir(parents=True, exist_ok=True)
    source = resources.files("xpolicylab") / "templates" / "policy"
    for filename in FILES:
        path = target / filename
        path.write_text(render((source / f"{filename}.tmpl").read_text(encoding="utf-8"), values), encoding="utf-8")
        if filename.endswith(".sh"):
            path.chmod(0o755)
    return target
