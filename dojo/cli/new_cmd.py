"""`dojo new task PACK/TASK`: start a task contribution from a commented skeleton that already passes.

It writes `PACK/tasks/TASK.yaml` (a pick-and-place task whose every field is explained where it stands, with a
working scripted expert) and `PACK/assets/TASK_block.yaml` (the pack's own object, a primitive block), so the
first `dojo validate --strict PACK/` passes and every later failure is the contributor's last edit. The words the
comments list (predicates, skills, dimensions) are read from their registries, so they are always the ones this
version accepts.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from dojo.compiler.spec_errors import did_you_mean
from dojo.compiler.spec_library import SpecLibrary
from dojo.compiler.taxonomy import taxonomy_of
from dojo.language import predicates as predicate_words
from dojo.language import skills as skill_words

EXAMPLE = "dojo new task my_pack/my_task"
ID = re.compile(r"^[a-z][a-z0-9_]*$")
KINDS = ("task",)

TASK = """\
# {task}: a task of the pack {pack}. Every field is described in specs/schemas/task.schema.json, and
# the README's "Contributing a task" says how a task is checked.
# Try:  dojo show task={task} packs=[{pack}] seed=0      (pictures of the scene, and the task's card)
#       dojo validate --strict {pack}/ --seeds 5           (is it sound? 20 seeds before you submit)
kind: task
version: 1
id: {task}                       # must equal the file name
title: Block onto the mat
# The capability it measures; one of: {dimensions}.
dimension: precision
embodiment: arx_x5_bimanual       # or piper_bimanual, piperx_bimanual
instruction: Put the block on the mat.
scene:
  # Fixtures stay where they are put: pos is [x, y, z] in metres (x to the robot's right, y away from it, the
  # table top's centre at 0, 0; z is the height of the object's base above the table top).
  fixtures:
    - {{name: mat, asset: mat_square, pos: [0.15, 0.05, 0.0]}}
  # Objects are dropped at a random free spot of their region (center and size in metres) for every seed.
  regions:
    start: {{center: [-0.15, -0.08], size: [0.12, 0.1]}}
  objects:
    - {{name: block, asset: {block}, region: start, yaw: [-30, 30]}}
# Success is a predicate on the simulator state, checked every control step. Predicates:
# {predicates}.
success: {{on: [block, mat]}}
# Score stages (weights): partial credit in order; a stage must not hold at the start.
stages:
  - {{name: lifted, when: {{lifted: [block, 0.05]}}, weight: 1}}
  - {{name: on_mat, when: {{on: [block, mat]}}, weight: 1}}
horizon: 500                      # control steps at 25 Hz; the expert's p90 x 1.2 must fit
# The scripted expert that proves the task solvable (dojo validate --strict runs it on every seed). Skills:
# {skills}.
expert:
  - {{skill: place, object: block, target: mat/top}}
  - {{skill: home}}
"""

ASSET = """\
# {block}: the pack's own object for {task}. Lengths are metres, masses kilograms; the origin is the centre of the
# object's footprint on the surface it rests on. A mesh geom is {{type: mesh, mesh: file.obj}} (closed, in metres).
kind: asset
version: 1
id: {block}
class: rigid
category: {block}
names: [block, cube]              # words instructions may use for it
mass: 0.05
friction: 1.0
rgba: [0.85, 0.35, 0.2, 1]
geoms:
  - {{type: box, size: [0.02, 0.02, 0.02], pos: [0, 0, 0.02]}}   # half-sizes: a 4 cm cube
"""


def new_main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="dojo new", description="Write a commented spec skeleton that already validates.",
        epilog=f"example:\n  {EXAMPLE}\n  (then: dojo validate --strict my_pack/ --seeds 5)",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("kind", help="what to write: task")
    parser.add_argument("where", type=Path, help="PACK/TASK: the pack folder (made if missing) and the task id")
    try:
        args = parser.parse_args(argv)
    except SystemExit as stop:
        return 0 if stop.code == 0 else 2
    if args.kind not in KINDS:
        print(f"dojo new: cannot write a '{args.kind}'{did_you_mean(args.kind, KINDS)}; one of {', '.join(KINDS)} "
              "(a policy: dojo policy new)", file=sys.stderr)
        return 2
    pack, task = args.where.parent, args.where.name
    block = f"{task}_block"
    library = SpecLibrary.load([])
    taken = {s.id for s in library.of_kind("task")} | {s.id for s in library.of_kind("asset")}
    problem = (f"'{task}' is not a task id (lower-case letters, digits and _, starting with a letter)"
               if not ID.match(task) or len(block) > 64 else
               f"'{task}' or '{block}' is a built-in id already: choose another name" if {task, block} & taken else
               None)
    files = {pack / "tasks" / f"{task}.yaml": TASK, pack / "assets" / f"{block}.yaml": ASSET}
    existing = [str(f) for f in files if f.exists()]
    if problem or existing:
        print(f"dojo new: {problem or 'would overwrite ' + ', '.join(existing)}", file=sys.stderr)
        return 2
    words = {"pack": str(pack).rstrip("/") or ".", "task": task, "block": block,
             "dimensions": ", ".join(taxonomy_of(library).ids),
             "predicates": ", ".join(predicate_words.names()), "skills": ", ".join(skill_words.names())}
    for file, template in files.items():
        file.parent.mkdir(parents=True, exist_ok=True)
        file.write_text(template.format(**words))
    steps = {f"dojo validate {words['pack']}/": "the schema, in seconds",
             f"dojo show task={task} packs=[{words['pack']}] seed=0": "look at it -> outputs/show/",
             f"dojo validate --strict {words['pack']}/ --seeds 5": "the full audit (20 seeds before you submit)"}
    width = max(map(len, steps))
    print(f"wrote {', '.join(map(str, files))}\nnext:\n" +
          "\n".join(f"  {command.ljust(width)}  # {why}" for command, why in steps.items()))
    return 0
