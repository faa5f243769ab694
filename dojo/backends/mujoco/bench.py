"""Throughput of the CPU backend: interactions (environment control steps) per second and reset latency.

`measure_cpu` is what `dojo bench` calls for the mujoco backend. It runs zero joint actions (every joint
driven towards 0, grippers closed: the arms move, so contacts and servos are exercised, not a resting scene),
refills slots whose episodes end exactly as the runtime would (continuous batching), and times the steps and
the resets separately. One control step = `plan.n_substeps` physics steps plus predicates and observations
without images.

`python -m dojo.backends.mujoco.bench PLAN.json... [--envs N] [--steps S] [--threads T]` prints the figures as
JSON. Besides the backend's figures it reports plain `mj_step` per CPU second for the first plan under the
same zero controls, so that the backend's overhead can be read off on a machine whose load varies.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from dojo.backends.actions import action_dim
from dojo.backends.registry import BackendOptions, make_backend


def measure_cpu(plans: Sequence[Any], num_envs: int, steps: int, num_threads: int | None = None,
                resets: int = 50) -> dict[str, Any]:
    """Step `num_envs` slots (plans cycled over the slots) `steps` control steps with zero joint actions.

    Returns interactions/s (env steps per wall second, resets excluded), interactions per CPU second of this
    process (all threads; a figure that other load on the machine disturbs much less), physics steps/s, the
    mean and max reset time in milliseconds (over `resets` resets of one slot), and the setup with the machine's
    1-minute load average before and after (other processes' load divides the wall-clock figures).
    """
    slots = [plans[k % len(plans)] for k in range(num_envs)]
    load_before = os.getloadavg()[0]
    with make_backend("mujoco", BackendOptions(settings={"threads": num_threads})) as backend:
        backend.load(slots)
        backend.reset()
        zero = np.zeros((num_envs, action_dim("joint", len(slots[0].robot["arm_joints"]) // 2)))
        step_time = cpu_time = 0.0
        for _ in range(steps):
            start, cpu_start = time.perf_counter(), time.process_time()
            result = backend.step(zero)
            step_time += time.perf_counter() - start
            cpu_time += time.process_time() - cpu_start
            if result.done.any():
                backend.reset(result.env_ids[result.done])
        reset_times = []
        for _ in range(resets):
            start = time.perf_counter()
            backend.reset([0])
            reset_times.append(time.perf_counter() - start)
        threads = backend.num_threads
    interactions = num_envs * steps / step_time
    raw = raw_physics_rate(slots[0], min(steps, 200) * slots[0].n_substeps)
    return {
        "backend": "mujoco",
        "tasks": sorted({p.task for p in plans}),
        "num_envs": num_envs,
        "steps": steps,
        "threads": threads,
        "cpus": os.cpu_count(),
        "load_average_1min": [load_before, os.getloadavg()[0]],
        "interactions_per_s": interactions,
        "interactions_per_cpu_s": num_envs * steps / cpu_time,
        "physics_steps_per_s": interactions * slots[0].n_substeps,
        "raw_mj_step_per_cpu_s": raw,
        "reset_ms_mean": 1000.0 * float(np.mean(reset_times)),
        "reset_ms_max": 1000.0 * float(np.max(reset_times)),
    }


def raw_physics_rate(plan: Any, nstep: int) -> float:
    """Plain `mj_step` per CPU second on one thread from the plan's initial state with zero controls."""
    model = plan.model()
    data = plan.initial_data(model)
    data.ctrl[:] = 0.0
    start = time.process_time()
    mujoco.mj_step(model, data, nstep=nstep)
    return nstep / (time.process_time() - start)


def main(argv: Sequence[str] | None = None) -> None:
    from dojo.compiler.plan import Plan

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("plans", nargs="+", type=Path, help="plan files (dojo compile output)")
    parser.add_argument("--envs", type=int, default=8)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--threads", type=int, default=None)
    args = parser.parse_args(argv)
    plans = [Plan.load(p) for p in args.plans]
    print(json.dumps(measure_cpu(plans, args.envs, args.steps, args.threads), indent=2))


if __name__ == "__main__":
    main()
