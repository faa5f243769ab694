"""The peer figure of the README: robosuite's TwoArmLift, stepped the way `dojo.backends.mujoco.bench` steps ours.

Run it in a throwaway environment (robosuite is not a RoboDojo dependency):

    python3.11 -m venv /tmp/rs && /tmp/rs/bin/pip install robosuite==1.5.2
    /tmp/rs/bin/python examples/peer_bench/robosuite_twoarmlift.py --steps 400

One environment, two Panda arms, no cameras and no renderer, zero actions of the default controller, on one
thread. Prints one JSON object: control steps per wall second and per CPU second of this process, plain
`mj_step` of the same model per CPU second, the environment's overhead over that bare physics, and the mean reset
time. CPU seconds are the figure to compare on a machine that other jobs load.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import mujoco
import numpy as np
import robosuite


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=400, help="timed control steps")
    parser.add_argument("--resets", type=int, default=5)
    args = parser.parse_args()
    env = robosuite.make("TwoArmLift", robots=["Panda", "Panda"], has_renderer=False,
                         has_offscreen_renderer=False, use_camera_obs=False, horizon=10 ** 9)
    env.reset()
    action = np.zeros(env.action_dim)
    env.step(action)  # the first step builds lazily initialised state: not what a step costs
    load_before = os.getloadavg()[0]
    wall, cpu = time.perf_counter(), time.process_time()
    for _ in range(args.steps):
        env.step(action)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    substeps = int(round(env.control_timestep / env.model_timestep))
    model, data = env.sim.model._model, env.sim.data._data
    nstep = args.steps * substeps
    raw = time.process_time()
    mujoco.mj_step(model, data, nstep=nstep)
    raw = nstep / (time.process_time() - raw)
    resets = []
    for _ in range(args.resets):
        start = time.perf_counter()
        env.reset()
        resets.append(time.perf_counter() - start)
    per_cpu_s = args.steps / cpu
    print(json.dumps({
        "env": "TwoArmLift", "robots": ["Panda", "Panda"], "robosuite": robosuite.__version__,
        "mujoco": mujoco.__version__, "steps": args.steps, "substeps_per_control_step": substeps,
        "control_steps_per_s": args.steps / wall, "control_steps_per_cpu_s": per_cpu_s,
        "raw_mj_step_per_cpu_s": raw, "raw_control_steps_per_cpu_s": raw / substeps,
        "overhead_over_bare_physics": 1.0 - per_cpu_s / (raw / substeps),
        "reset_ms_mean": 1000.0 * float(np.mean(resets)), "load_average_1min": [load_before, os.getloadavg()[0]],
    }))


if __name__ == "__main__":
    main()
