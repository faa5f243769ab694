"""`dojo console`: serve the RealEval operator console for a real suite on one robot (the emulator by default).

Examples:
    dojo console suite=robodojo_real_piper policy.url=ws://HOST:PORT [token=...] [port=8787]
    dojo console scores outputs/robodojo_real_piper/console/my_policy/results.sqlite
    dojo console add-rater alice [raters=PATH]      (prints alice's token once)
    dojo console remove-rater alice [raters=PATH]
    dojo console suite=robodojo_real_piper policy=zero backend.driver=piper backend.can=[can_left,can_right]

Arguments are `key=value` (dotted keys, lists in brackets), as for `dojo run`. The trials go into the results
store `<out>/results.sqlite` (default out: `outputs/<suite>/console/<policy>`), their videos beside it, the
reference layouts under `layouts` (default `<out>/layouts`). The operator's token guards every page; it is
`token=`, else `$DOJO_CONSOLE_TOKEN`, else a new one printed once. Raters log in with their own tokens, which
open only the rater pages: `add-rater` issues one and keeps its hash in the raters file (`raters=`, default
`<results root>/console/raters.json`), which the running console reads again when it changes. The console
listens on 127.0.0.1 unless `host=` says otherwise: it commands a robot, so put it on a network only behind
your lab's own access control.

The e-stop has a process of its own (for the PiPER, emulated or not), listening on `estop_port` (default: the
console's port + 1) of the same host: the page's E-STOP button and Escape key go there, so a press holds the arms
without waiting for the console's own process.

`dojo console scores STORE` prints the raters' verdicts by policy and task: the one place policies are named.
"""

from __future__ import annotations

import os
import secrets
import sys
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from dojo.evaluation.evaluate import run_id_for

DEFAULTS: dict[str, Any] = {
    "suite": None, "packs": [], "tasks": None, "episodes": None, "seeds": None, "plans": None,
    "policy": {"name": "zero"},
    "backend": {"name": "real", "driver": "emulator", "can": None, "emulator": {"bus": "dojo_host"}},
    "width": None, "height": None, "host": "127.0.0.1", "port": 8787, "estop_port": None, "token": None,
    "out": None, "layouts": None, "raters": None,
}
"""The emulator's buses are `dojo_host` ones, which the e-stop's own process can reach (`dojo.realeval.estop`)."""


def console_config(argv: list[str]) -> Any:
    """The console's configuration: DEFAULTS with the `key=value` arguments over them."""
    if any(a in ("-h", "--help") for a in argv):
        print(__doc__)
        raise SystemExit(0)
    bad = [a for a in argv if "=" not in a]
    if bad:
        raise ValueError(f"dojo console takes key=value arguments, got {bad[0]!r}")
    argv = [f"policy.name={a.split('=', 1)[1]}" if a.startswith("policy=") else a for a in argv]  # as dojo run
    cfg = OmegaConf.merge(OmegaConf.create(DEFAULTS), OmegaConf.from_dotlist(argv))
    if not cfg.suite:
        raise ValueError("dojo console needs suite=<a real suite>, e.g. suite=robodojo_real_piper")
    return cfg


def build_session(cfg: Any) -> Any:
    """The console session `cfg` describes: the suite compiled, the policy opened, the robot configured."""
    from dojo.cli.run_cmd import DEFAULT_PLAN_CACHE
    from dojo.compiler.horizon import horizons_file, load_demo_lengths
    from dojo.compiler.spec_library import SpecLibrary
    from dojo.compiler.suite_compile import compile_suite
    from dojo.evaluation.camera_budget import image_size
    from dojo.evaluation.policy_link import open_policy
    from dojo.evaluation.results_store import ResultsStore
    from dojo.realeval.session import ConsoleSession

    library = SpecLibrary.load([Path(p) for p in cfg.packs])
    suite = library.get("suite", str(cfg.suite))
    seeds = list(cfg.seeds) if cfg.seeds is not None else None
    tasks = list(cfg.tasks) if cfg.tasks is not None else None
    plan_dir = Path(cfg.plans) if cfg.plans else DEFAULT_PLAN_CACHE / suite.id
    stats = compile_suite(library, suite, plan_dir, seeds=seeds, episodes=cfg.episodes, tasks=tasks,
                          demo_lengths=load_demo_lengths(horizons_file("auto")))
    queue = list(stats.episodes)
    if not queue:
        raise ValueError(f"suite {suite.id} has no trials to run")
    embodiment = library.get("task", queue[0].task).data["embodiment"]
    policy_cfg = OmegaConf.to_container(cfg.policy, resolve=True)
    policy = open_policy(policy_cfg, embodiment)  # type: ignore[arg-type]
    try:
        meta = policy.metadata
        from dojo.compiler.plan import Plan

        robot_cameras = Plan.load(queue[0].plan_path).cameras
        cameras = tuple(meta.cameras) + tuple(c for c in robot_cameras if c not in meta.cameras)
        width, height, _ = image_size(meta, cfg.width, cfg.height)
        backend: dict[str, Any] = OmegaConf.to_container(cfg.backend, resolve=True)  # type: ignore[assignment]
        identity = {"suite": suite.id, "policy": meta.name, "policy_config": policy_cfg, "backend": "real",
                    "driver": backend["driver"], "seeds": seeds, "episodes": cfg.episodes, "tasks": tasks,
                    "console": True}
        root = Path(os.environ.get("DOJO_OUTPUTS", "outputs"))
        out = Path(cfg.out) if cfg.out else root / suite.id / "console" / meta.name
        layouts = Path(cfg.layouts) if cfg.layouts else out / "layouts"
        run_id = run_id_for(identity)
        with ResultsStore(out / "results.sqlite") as store:  # the same session again resumes its run
            store.ensure_run(run_id, identity)
        return ConsoleSession(queue, policy, run_id, out / "results.sqlite", out, backend, cameras, (width, height),
                              layouts)
    except BaseException:
        policy.close()
        raise


def console_main(argv: list[str]) -> int:
    """`dojo console key=value ...`: build the session and serve it until interrupted; `dojo console scores
    STORE`: the raters' verdicts; `add-rater` / `remove-rater NAME`: the raters' tokens."""
    if argv[:1] == ["scores"]:
        return _print_scores(argv[1:])
    if argv[:1] in (["add-rater"], ["remove-rater"]):
        return _manage_rater(argv[0], argv[1:])
    import uvicorn

    from dojo.realeval.app import COOKIE, create_app
    from dojo.realeval.raters import RaterRegistry, default_raters_file

    cfg = console_config(argv)
    token = cfg.token or os.environ.get("DOJO_CONSOLE_TOKEN")
    if not token:
        token = secrets.token_urlsafe(18)
        print(f"console token (give it to the operators): {token}", flush=True)
    raters = RaterRegistry(Path(cfg.raters) if cfg.raters else default_raters_file())
    if not raters.names():
        print(f"no raters in {raters.path} yet: `dojo console add-rater NAME` issues a rater's token", flush=True)
    session = build_session(cfg)
    estop_port = int(cfg.estop_port) if cfg.estop_port is not None else int(cfg.port) + 1
    session.serve_estop(str(token), COOKIE, str(cfg.host), estop_port)
    try:
        print(f"RealEval console: http://{cfg.host}:{cfg.port}/  ({len(session.trials)} trials; results "
              f"{session.store_path}; raters {raters.path})", flush=True)
        uvicorn.run(create_app(session, str(token), raters), host=str(cfg.host), port=int(cfg.port),
                    log_level="warning")
    finally:
        session.close()
    return 0


def _manage_rater(action: str, argv: list[str]) -> int:
    """`add-rater NAME [raters=PATH]` prints the new token once; `remove-rater NAME [raters=PATH]` revokes it."""
    from dojo.realeval.raters import RaterRegistry, default_raters_file

    names = [a for a in argv if "=" not in a]
    options = dict(a.split("=", 1) for a in argv if "=" in a)
    if len(names) != 1 or set(options) - {"raters"}:
        raise ValueError(f"usage: dojo console {action} NAME [raters=PATH]")
    raters = RaterRegistry(Path(options["raters"]) if "raters" in options else default_raters_file())
    if action == "add-rater":
        token = raters.add(names[0])
        print(f"rater {names[0]}'s token (shown once; give it to them): {token}")
    else:
        raters.remove(names[0])
        print(f"rater {names[0]} removed from {raters.path}")
    return 0


def _print_scores(argv: list[str]) -> int:
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    from dojo.evaluation.results_store import resolve_store_path
    from dojo.realeval.scores import real_scores

    if len(argv) != 1:
        raise ValueError("usage: dojo console scores STORE (a results.sqlite or its run folder)")
    table = Table(title="RealEval: raters' verdicts")
    for column in ("policy", "task", "trials", "settled", "flagged", "open", "success %", "score", "appeals"):
        table.add_column(column, justify="left" if column in ("policy", "task") else "right")
    for s in real_scores(resolve_store_path(argv[0])):
        table.add_row(escape(s.policy), escape(s.task), str(s.trials), str(s.settled), str(s.flagged), str(s.open),
                      "-" if s.success_rate is None else f"{s.success_rate:.1f}",
                      "-" if s.score is None else f"{s.score:.1f}", str(s.appeals))
    Console(soft_wrap=True).print(table)
    return 0


if __name__ == "__main__":
    sys.exit(console_main(sys.argv[1:]))
