"""The kernel warm-up's stand-in worker (`test_kernel_warmup.py`), in a module of its own: the worker processes
import it by name, and it must import nothing that depends on how pytest set up `sys.path` (a `conftest`)."""

from __future__ import annotations

import json
import os
import uuid
from pathlib import Path
from typing import Any


def record_job(job: Any) -> float:
    """Stand-in worker: writes what it received (and its process id) where the test says; fails on request."""
    if job.key == os.environ.get("WARMUP_FAIL"):
        raise RuntimeError("out of GPU memory")
    record = {"key": job.key, "pid": os.getpid(), "nbody": job.model.nbody, "ngeom": job.model.ngeom,
              "contacts": job.contacts, "rows": job.rows}
    (Path(os.environ["WARMUP_RECORDS"]) / uuid.uuid4().hex).write_text(json.dumps(record))
    return 0.0
