"""`dojo compile` and `dojo show`: the compiler's commands (configuration in dojo/cli/config/)."""

from __future__ import annotations

import sys
from pathlib import Path

from omegaconf import DictConfig

from dojo.backends.mujoco.render import ensure_headless_gl


def compile_task(cfg: DictConfig) -> int:
    """Compile the chosen suite's plans into `out` and print what was compiled and what was reused."""
    from dojo.compiler.horizon import horizons_file, load_demo_lengths
    from dojo.compiler.spec_library import SpecLibrary
    from dojo.compiler.suite_compile import compile_suite

    library = SpecLibrary.load([Path(p) for p in cfg.packs])
    suite = library.get("suite", cfg.suite.id)
    seeds = list(cfg.seeds) if cfg.seeds is not None else None
    demos = load_demo_lengths(horizons_file(cfg.horizons))
    stats = compile_suite(library, suite, Path(cfg.out), jobs=cfg.jobs, seeds=seeds, episodes=cfg.episodes,
                          demo_lengths=demos, tasks=list(cfg.tasks) if cfg.tasks is not None else None)
    print(stats.summary(suite.id))
    if note := stats.compiler_note():
        print(note)
    return 0


def show_task(cfg: DictConfig) -> int:
    """Render a plan, a task's scene or a robot from every camera (and an overview) to PNG files; for a task, also
    its task card (Markdown) linking the images."""
    ensure_headless_gl()
    import mujoco

    from dojo.backends.mujoco.render import render_cameras, render_overview, save_png
    from dojo.backends.world_actors import first_state
    from dojo.compiler.plan import Plan, compile_plan
    from dojo.compiler.robot_emit import apply_home, build_robot_world
    from dojo.compiler.spec_library import SpecLibrary
    from dojo.compiler.task_card import task_card

    out = Path(cfg.out)
    if cfg.plan is not None:
        plan = Plan.load(Path(cfg.plan))
        model, cameras, label = plan.model(), plan.cameras, f"{plan.task}-{plan.setting}-{plan.seed}"
        data = first_state(plan, model)
    elif cfg.task is not None:
        library = SpecLibrary.load([Path(p) for p in cfg.packs])
        task = library.get("task", cfg.task)
        plan = compile_plan(library, task, cfg.setting, int(cfg.seed))
        model, cameras, label = plan.model(), plan.cameras, f"{task.id}-{cfg.setting}-{cfg.seed}"
        data = first_state(plan, model)
        print(f"instruction: {plan.instruction}")
    elif cfg.robot is not None:
        library = SpecLibrary.load([Path(p) for p in cfg.packs])
        world, handles = build_robot_world(library.get("robot", cfg.robot.id).data)
        model = world.compile()
        data = mujoco.MjData(model)
        apply_home(model, data, handles)
        cameras, label = list(handles.cameras), cfg.robot.id
    else:
        print("dojo show: name what to show: plan=PATH, task=ID (with seed= and setting=), or robot=ID",
              file=sys.stderr)
        return 2
    images = render_cameras(model, data, cameras, int(cfg.width), int(cfg.height))
    images["overview"] = render_overview(model, data, int(cfg.width), int(cfg.height))
    for name, image in images.items():
        save_png(image, out / f"{label}_{name}.png")
        print(out / f"{label}_{name}.png")
    if cfg.task is not None:
        card = out / f"{label}.md"
        card.write_text(task_card(task, plan.instruction, {n: f"{label}_{n}.png" for n in images}))
        print(card)
    if cfg.usd:
        from dojo.compiler.usd_io import export_model_usd

        print(export_model_usd(model, data, out / f"{label}.usda"))
    return 0


def bench_task(cfg: DictConfig) -> int:
    """`dojo bench sim|render|kernels`: run the benchmark and print its one JSON line of figures."""
    import json

    from omegaconf import OmegaConf

    settings = OmegaConf.to_container(cfg, resolve=True)
    if cfg.what == "sim":
        from dojo.bench.sim_bench import bench_sim
        figures = bench_sim(settings)
    elif cfg.what == "render":
        ensure_headless_gl()
        from dojo.bench.render_bench import bench_render
        figures = bench_render(settings)
    elif cfg.what == "kernels":
        from dojo.bench.warp_modules import bench_kernels
        figures = bench_kernels(settings)
    else:
        print(f"dojo bench: unknown benchmark '{cfg.what}'; one of sim, render, kernels, policy, ray",
              file=sys.stderr)
        return 2
    print(json.dumps(figures))
    return 0
