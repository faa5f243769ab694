"""The `dojo` command line: one entry point, one subcommand per job.

Configurable jobs (`compile`, `run`, `show`, `bench`) are Hydra applications (`key=value` overrides, `-m`
sweeps, `--cfg job`); `validate` and `list` take plain arguments because they act on paths and names, not on a
configuration. No Python traceback reaches the user: spec problems print as `file:line:col: path: message`,
anything unexpected prints one line (set DOJO_DEBUG=1 to see the traceback).
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from typing import Callable

from dojo.compiler.spec_errors import SpecError, did_you_mean
from dojo.evaluation.termination import EXIT_CODE as TERMINATED_EXIT
from dojo.evaluation.termination import Terminated, stopping_on_sigterm


@dataclass(frozen=True)
class Command:
    """A subcommand: what it does (one line) and how to call it (one example)."""

    summary: str
    example: str
    run: Callable[[list[str]], int]


def _what_word(argv: list[str]) -> list[str]:
    """`dojo bench sim ...`: the first bare word names what to measure, as the override `what=sim`."""
    if argv and "=" not in argv[0] and not argv[0].startswith("-"):
        return [f"what={argv[0]}"] + argv[1:]
    return argv


def _hydra(name: str, task_name: str) -> Callable[[list[str]], int]:
    """A configurable command: Hydra composes dojo/cli/config/<name>.yaml with the overrides, then runs it."""
    def run(argv: list[str]) -> int:
        from dojo.cli import compile_cmd, run_cmd
        from dojo.datagen import collect
        from dojo.cli.hydra_app import run_hydra_command
        module = {"run": run_cmd, "collect": collect}.get(name, compile_cmd)
        return run_hydra_command(name, name, _jobs_flag(argv), getattr(module, task_name))
    return run


def _jobs_flag(argv: list[str]) -> list[str]:
    """`-j N` (or `-jN`), the usual spelling for parallel work, as the Hydra override `jobs=N`."""
    out, i = [], 0
    while i < len(argv):
        if argv[i] == "-j" and i + 1 < len(argv):
            out.append(f"jobs={argv[i + 1]}")
            i += 2
            continue
        out.append(f"jobs={argv[i][2:]}" if argv[i].startswith("-j") and argv[i][2:].isdigit() else argv[i])
        i += 1
    return out


def _validate(argv: list[str]) -> int:
    from dojo.cli.validate_cmd import validate_main
    return validate_main(argv)


def _policy(argv: list[str]) -> int:
    """`dojo policy serve|check|new ...`: XPolicyLab's own commands, with the same arguments."""
    from xpolicylab import cli as xpl

    commands = {"serve": xpl.serve_main, "check": xpl.check_main, "new": xpl.new_main}
    if not argv or argv[0] in ("-h", "--help"):
        print(f"{COMMANDS['policy'].summary}\n\nusage: dojo policy serve|check|new [key=value ...]\n\nexamples:\n"
              "  dojo policy serve policy=zero protocol=xpolicylab port=19000\n"
              "  dojo policy check url=ws://127.0.0.1:19000 embodiment=arx_x5_bimanual\n"
              "  dojo policy new my_policy\n\nRun 'dojo policy <command> --help' for its arguments.")
        return 0 if argv else 2
    if argv[0] not in commands:
        print(f"dojo policy: unknown command '{argv[0]}'{did_you_mean(argv[0], commands)}; "
              f"one of {', '.join(commands)}", file=sys.stderr)
        return 2
    return commands[argv[0]](argv[1:])


def _bench(argv: list[str]) -> int:
    """`dojo bench policy ...` is XPolicyLab's link benchmark; `dojo bench ray ...` times `dojo run` over Ray
    workers and `dojo bench served ...` against a served policy, socket against shared memory (their other
    arguments are the run's); `sim` and `render` are Hydra-configured."""
    if argv and argv[0] == "policy":
        from xpolicylab.cli import bench_main
        return bench_main(argv[1:])
    if argv and argv[0] == "ray":
        from dojo.bench.ray_bench import bench_ray_main
        return bench_ray_main(argv[1:])
    if argv and argv[0] == "served":
        from dojo.bench.served_bench import bench_served_main
        return bench_served_main(argv[1:])
    return _hydra("bench", "bench_task")(_what_word(argv))


def _report(argv: list[str]) -> int:
    from dojo.report.make_report import report_main
    return report_main(argv)


def _doctor(argv: list[str]) -> int:
    from dojo.cli.doctor import doctor_main
    return doctor_main(argv)


def _console(argv: list[str]) -> int:
    from dojo.realeval.cli import console_main
    return console_main(argv)


def _list(argv: list[str]) -> int:
    from dojo.cli.list_cmd import list_main
    return list_main(argv)


def _new(argv: list[str]) -> int:
    from dojo.cli.new_cmd import new_main
    return new_main(argv)


COMMANDS: dict[str, Command] = {
    "validate": Command("Check spec files against the schemas and each other; --strict audits a task pack in full.",
                        "dojo validate --strict my_pack/ --seeds 20 --junit report.xml", _validate),
    "list": Command("List the installed tasks, assets, robots or suites.", "dojo list tasks", _list),
    "new": Command("Write a commented task skeleton (and its asset) into a task pack, ready to validate.",
                   "dojo new task my_pack/my_task", _new),
    "compile": Command("Compile a suite's specs into content-addressed plans.",
                       "dojo compile suite=robodojo_sim_mini -j 2", _hydra("compile", "compile_task")),
    "show": Command("Render a plan or a task's scene from every camera to PNG (and USD).",
                    "dojo show task=stack_blocks seed=3 setting=random", _hydra("show", "show_task")),
    "run": Command("Evaluate a policy on a suite and score it.",
                   "dojo run suite=robodojo_sim_mini policy.url=ws://127.0.0.1:19000", _hydra("run", "run_task")),
    "collect": Command("Record demonstrations of a task as HDF5 episodes and a LeRobot v3.0 dataset.",
                       "dojo collect task=stack_blocks n=100 policy=oracle", _hydra("collect", "collect_task")),
    "bench": Command("Measure simulation, rendering, policy-link, served end-to-end or Ray scaling throughput (one "
                     "JSON line).",
                     "dojo bench sim backend=mujoco num_envs=32 steps=200", _bench),
    "report": Command("Write the JSON and HTML report (leaderboard) of one or more runs.",
                      "dojo report outputs/robodojo_sim_mini/zero outputs/robodojo_sim_mini/random", _report),
    "policy": Command("Serve, check or create a policy (XPolicyLab).",
                      "dojo policy serve policy=zero port=19000", _policy),
    "console": Command("Serve the RealEval operator console: a real suite's trials on a robot (or its emulator).",
                       "dojo console suite=robodojo_real_piper policy.url=ws://127.0.0.1:19000", _console),
    "doctor": Command("Print versions, devices and where results and caches are (paste it into bug reports).",
                      "dojo doctor", _doctor),
}


def _usage() -> str:
    width = max(len(n) for n in COMMANDS)
    lines = ["usage: dojo <command> [arguments]", "",
             "RoboDojo: a declarative benchmark compiler for robot manipulation policies.", "", "commands:"]
    for name, cmd in COMMANDS.items():
        lines.append(f"  {name:<{width}}  {cmd.summary}")
    lines += ["", "examples:"] + [f"  {cmd.example}" for cmd in COMMANDS.values()]
    lines += ["", "Run 'dojo <command> --help' for a command's arguments."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `dojo` console script."""
    # MuJoCo picks its GL platform when first imported, and any subcommand may import it: choose the headless
    # one now (EGL, else OSMesa, else none: a GPU server without libEGL still imports mujoco), unless the user chose.
    from dojo.backends.gl_platform import choose_gl_platform
    choose_gl_platform()
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0 if argv else 2
    if argv[0] in ("-V", "--version"):
        from importlib.metadata import version
        print(f"robodojo {version('robodojo')}")
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"dojo: unknown command '{name}'{did_you_mean(name, COMMANDS)}\n\n{_usage()}", file=sys.stderr)
        return 2
    try:
        with stopping_on_sigterm():
            return COMMANDS[name].run(rest)
    except SpecError as err:
        print(err, file=sys.stderr)
        return 1
    except Terminated:
        print(f"dojo {name}: stopped by SIGTERM", file=sys.stderr)
        return TERMINATED_EXIT
    except KeyboardInterrupt:
        print(f"dojo {name}: interrupted", file=sys.stderr)
        return 130
    except Exception as err:  # the last line of defence: one clear line, never a traceback, unless debugging
        if os.environ.get("DOJO_DEBUG"):
            raise
        print(f"dojo {name}: error: {type(err).__name__}: {err} (set DOJO_DEBUG=1 for the traceback)",
              file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
