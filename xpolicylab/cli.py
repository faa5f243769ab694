"""The ``xpolicylab`` command: ``serve``, ``check``, ``new`` and ``bench``, with Hydra-style key=value arguments.

``dojo policy serve|check|new`` and ``dojo bench policy`` call ``serve_main``/``check_main``/``new_main``/
``bench_main`` with the same argument list, so both front ends behave identically. Every entry point returns a
process exit status: 0 success, 1 a failed check, 2 bad arguments.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import sys
from collections.abc import Callable, Sequence

from xpolicylab.args import Option, UsageError, closest, help_text, parse
from xpolicylab.embodiments import CAMERAS

SERVE_OPTIONS = (
    Option("policy", "str", "zero", "zero | random | replay | package.module:Class | path/to/model.py or its folder"),
    Option("protocol", "str", "xpolicylab", "wire dialect: xpolicylab (native) or openpi"),
    Option("host", "str", "127.0.0.1", "interface to bind (0.0.0.0 for remote evaluation)"),
    Option("port", "int", 19000, "TCP port (0 picks a free one)"),
    Option("token", "str", None, "bearer token clients must send; defaults to $XPOLICYLAB_TOKEN"),
    Option("max_frame_mb", "float", 512.0, "largest accepted message, MiB; larger ones are closed with 1009"),
    Option("request_timeout_s", "float", 120.0, "longest a model call may take before a timeout error"),
    Option("shared_memory", "bool", True, "read large arrays from /dev/shm when a client on this host (loopback) "
           "sends references (native dialect)"),
    Option("embodiment", "str", "arx_x5_bimanual", "robot the reference policies act for"),
    Option("action_mode", "str", "joint", "joint (D=14) or ee (D=16), for the reference policies"),
    Option("chunk_size", "int", 8, "actions per chunk, for the reference policies"),
    Option("seed", "int", 0, "seed of the random policy"),
    Option("max_delta", "float", 0.05, "largest random step (rad or m) of the random policy"),
    Option("episode", "str", None, "recorded episode (.npz) for the replay policy"),
    Option("cameras", "list", (), "cameras the reference policies ask for (and ignore): tests of the image path"),
    Option("width", "int", None, "image width the reference policies ask for (none: any)"),
    Option("height", "int", None, "image height the reference policies ask for (none: any)"),
    Option("log_level", "str", "info", "debug | info | warning | error"),
)
CHECK_OPTIONS = (
    Option("url", "str", None, "policy server to check, e.g. ws://127.0.0.1:19000 (required)"),
    Option("protocol", "str", "xpolicylab", "wire dialect: xpolicylab or openpi"),
    Option("embodiment", "str", "arx_x5_bimanual", "arx_x5_bimanual | piper_bimanual | piperx_bimanual"),
    Option("cameras", "list", CAMERAS, "cameras to send images for"),
    Option("width", "int", 640, "image width"),
    Option("height", "int", 480, "image height"),
    Option("n", "int", 20, "number of single-observation infer requests"),
    Option("batch", "int", 4, "environments in the batched infer check (0 skips it)"),
    Option("depth", "bool", False, "also send uint16 depth images"),
    Option("token", "str", None, "bearer token; defaults to $XPOLICYLAB_TOKEN"),
    Option("timeout_s", "float", 30.0, "deadline for connecting and for each reply"),
    Option("connect_attempts", "int", 8, "connection attempts (exponential backoff) before giving up"),
    Option("seed", "int", 0, "seed of the synthetic observations"),
)
NEW_OPTIONS = (
    Option("dir", "str", ".", "folder in which the package folder NAME is created"),
    Option("task", "str", "my_task", "task the policy is trained for (a task id, e.g. stack_bowls)"),
    Option("robot", "str", "arx_x5_bimanual", "embodiment"),
    Option("action_type", "str", "joint", "joint or ee"),
    Option("chunk_size", "int", 8, "actions per chunk"),
    Option("seed", "int", 0, "experiment seed"),
)
BENCH_OPTIONS = (
    Option("protocols", "list", ("xpolicylab", "openpi"), "dialects to measure"),
    Option("batch", "int", 64, "observations per batched request"),
    Option("width", "int", 640, "image width"),
    Option("height", "int", 480, "image height"),
    Option("cameras", "list", CAMERAS, "cameras per observation"),
    Option("n", "int", 20, "timed batched round trips"),
    Option("warmup", "int", 3, "untimed round trips first"),
    Option("single_n", "int", 50, "timed single-observation round trips"),
    Option("embodiment", "str", "arx_x5_bimanual", "robot of the synthetic observations"),
    Option("url", "str", None, "bench this running zero-policy server instead of spawning one per dialect"),
    Option("shared_memory", "list", ("auto",), "client modes to measure in turn, e.g. [off,on]: auto | on | off "
           "(large arrays through /dev/shm; xpolicylab dialect, openpi always off)"),
    Option("layouts", "list", ("columns",), "batch layouts to measure in turn, e.g. [list,columns]: columns (one "
           "array per camera for the batch) | list (one observation per environment); xpolicylab dialect"),
)

COMMANDS: dict[str, tuple[str, str]] = {
    "serve": ("Serve a policy over WebSocket + MessagePack (native XPolicyLab or openpi dialect).",
              "xpolicylab serve policy=zero protocol=openpi port=19000 host=127.0.0.1"),
    "check": ("Check a running policy server offline: synthetic observations, every reply validated "
              "(shape, dtype, finite, joint limits, chunk length, mode), latency percentiles, pass/fail report.",
              "xpolicylab check url=ws://127.0.0.1:19000 embodiment=arx_x5_bimanual "
              "cameras=[head,left_wrist,right_wrist] width=640 height=480 n=20"),
    "new": ("Write a policy package (install/process_data/train/eval scripts, model.py, deploy.py, deploy.yml) "
            "that passes `xpolicylab check` as generated.",
            "xpolicylab new my_policy --dir policies task=stack_bowls robot=arx_x5_bimanual"),
    "bench": ("Loopback round-trip latency and throughput of the zero policy: a batch of observations per request, "
              "native and openpi dialects; prints one JSON line.",
              "xpolicylab bench batch=64 width=640 height=480 n=20"),
}
_OPTIONS = {"serve": SERVE_OPTIONS, "check": CHECK_OPTIONS, "new": NEW_OPTIONS, "bench": BENCH_OPTIONS}


def _help(command: str) -> str:
    summary, example = COMMANDS[command]
    usage = f"xpolicylab {command}" + (" NAME [--dir D]" if command == "new" else "")
    return help_text(usage, summary, _OPTIONS[command], example)


def _wants_help(args: Sequence[str]) -> bool:
    return any(a in ("-h", "--help") for a in args)


def _exit_2_on_usage_error(command: str) -> Callable[[Callable[[Sequence[str]], int]], Callable[[Sequence[str]], int]]:
    """Make a ``*_main`` print a UsageError and return 2, so every caller (ours or dojo's) gets the same."""
    def wrap(fn: Callable[[Sequence[str]], int]) -> Callable[[Sequence[str]], int]:
        @functools.wraps(fn)
        def run(args: Sequence[str]) -> int:
            try:
                return fn(list(args))
            except UsageError as exc:
                print(f"xpolicylab {command}: {exc}", file=sys.stderr)
                return 2
        return run
    return wrap


@_exit_2_on_usage_error("serve")
def serve_main(args: Sequence[str]) -> int:
    """``xpolicylab serve`` / ``dojo policy serve``: blocks until interrupted."""
    if _wants_help(args):
        print(_help("serve"))
        return 0
    opts, policy_extra = parse(args, SERVE_OPTIONS, "xpolicylab serve", free_prefix="policy")
    from xpolicylab.policies import load_policy
    from xpolicylab.server import ServerConfig, run_server

    logging.basicConfig(level=str(opts["log_level"]).upper(), format="%(asctime)s %(name)s %(levelname)s %(message)s")
    config = {k: opts[k] for k in ("embodiment", "action_mode", "chunk_size", "seed", "max_delta", "cameras",
                                   "width", "height")}
    if opts["episode"] is not None:
        config["episode"] = opts["episode"]
    config.update(policy_extra)
    try:
        server_config = ServerConfig(host=opts["host"], port=opts["port"], protocol=opts["protocol"],
                                     token=opts["token"] or os.environ.get("XPOLICYLAB_TOKEN") or None,
                                     max_frame_mb=opts["max_frame_mb"], request_timeout_s=opts["request_timeout_s"],
                                     shared_memory=opts["shared_memory"])
        model = load_policy(opts["policy"], config)
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    run_server(model, server_config)
    return 0


@_exit_2_on_usage_error("check")
def check_main(args: Sequence[str]) -> int:
    """``xpolicylab check [URL] [key=value ...]`` / ``dojo policy check``: 0 when every check passes, else 1."""
    if _wants_help(args):
        print(_help("check"))
        return 0
    if args and args[0].startswith(("ws://", "wss://")):  # `xpolicylab check ws://...`, the URL first
        args = [f"url={args[0]}", *args[1:]]
    opts, _ = parse(args, CHECK_OPTIONS, "xpolicylab check")
    if not opts["url"]:
        raise UsageError("`xpolicylab check` needs url=ws://HOST:PORT")
    from xpolicylab.checker import CheckConfig, run_check
    from xpolicylab.embodiments import get_embodiment

    try:
        get_embodiment(opts["embodiment"])
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    if opts["protocol"] not in ("xpolicylab", "openpi"):
        hint = closest(opts["protocol"], ["xpolicylab", "openpi"])
        raise UsageError(f"protocol must be xpolicylab or openpi; did you mean {hint!r}?")
    report = run_check(CheckConfig(
        url=opts["url"], protocol=opts["protocol"], embodiment=opts["embodiment"], cameras=tuple(opts["cameras"]),
        width=opts["width"], height=opts["height"], n=opts["n"], batch=opts["batch"], depth=opts["depth"],
        token=opts["token"] or os.environ.get("XPOLICYLAB_TOKEN") or None, timeout_s=opts["timeout_s"],
        connect_attempts=opts["connect_attempts"], seed=opts["seed"]))
    print(report.format())
    return 0 if report.passed else 1


@_exit_2_on_usage_error("new")
def new_main(args: Sequence[str]) -> int:
    """``xpolicylab new NAME [--dir D] [key=value ...]`` / ``dojo policy new``."""
    if _wants_help(args):
        print(_help("new"))
        return 0
    names, rest, tokens = [], [], list(args)
    while tokens:
        token = tokens.pop(0)
        if token == "--dir":
            if not tokens:
                raise UsageError("--dir needs a folder")
            rest.append(f"dir={tokens.pop(0)}")
        elif token.startswith("--dir="):
            rest.append(token[2:])
        elif "=" in token:
            rest.append(token)
        else:
            names.append(token)
    if len(names) != 1:
        raise UsageError("`xpolicylab new` needs exactly one NAME, e.g. xpolicylab new my_policy --dir policies")
    opts, _ = parse(rest, NEW_OPTIONS, "xpolicylab new")
    from xpolicylab.template import new_policy

    directory = opts.pop("dir")
    try:
        path = new_policy(names[0], directory, **opts)
    except (ValueError, FileExistsError) as exc:
        raise UsageError(str(exc)) from exc
    print(f"created policy package {path}; try: cd {path} && ./eval.sh")
    return 0


@_exit_2_on_usage_error("bench")
def bench_main(args: Sequence[str]) -> int:
    """``xpolicylab bench`` / ``dojo bench policy``: prints exactly one JSON line."""
    if _wants_help(args):
        print(_help("bench"))
        return 0
    opts, _ = parse(args, BENCH_OPTIONS, "xpolicylab bench")
    from xpolicylab.bench import BenchConfig, layouts_arg, protocols_arg, run_bench, shared_memory_arg

    try:
        protocols = protocols_arg(opts.pop("protocols"))
        opts["shared_memory"] = shared_memory_arg(opts["shared_memory"])
        opts["layouts"] = layouts_arg(opts["layouts"])
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    opts["cameras"] = tuple(opts["cameras"])
    print(json.dumps(run_bench(BenchConfig(protocols=protocols, **opts))), flush=True)
    return 0


MAINS: dict[str, Callable[[Sequence[str]], int]] = {
    "serve": serve_main, "check": check_main, "new": new_main, "bench": bench_main,
}


def _top_help() -> str:
    lines = ["usage: xpolicylab {serve,check,new,bench} [key=value ...]", "",
             "XPolicyLab: integrate a robot policy once, evaluate it anywhere.", "", "commands:"]
    lines += [f"  {name:<6} {summary}" for name, (summary, _) in COMMANDS.items()]
    lines += ["", "`xpolicylab COMMAND --help` shows the keys of a command and an example."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``xpolicylab`` console script."""
    args = sys.argv[1:] if argv is None else list(argv)
    if not args or args[0] in ("-h", "--help"):
        print(_top_help())
        return 0 if args else 2
    command, rest = args[0], args[1:]
    if command not in MAINS:
        print(f"xpolicylab: unknown command {command!r}; did you mean {closest(command, list(MAINS))!r}?\n"
              f"{_top_help()}", file=sys.stderr)
        return 2
    return MAINS[command](rest)


if __name__ == "__main__":
    sys.exit(main())
