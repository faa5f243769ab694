"""The checks of `dojo validate --strict`, in order, as data: one `Check` per thing a contributed task must prove.

A task is checked in this order and stops at its first failure (a warning does not stop it): the schema and
references, safety, asset sanity, determinism, stability, solvability, no trivial success, horizon. Each check
reads what the audit gathered for the task (`Audit`: its spec, its plans compiled twice, its policies' episodes)
and returns one `CheckResult`: a status, one figure a person can judge at a glance, and the findings behind it.
The terminal table, the JSON and the JUnit XML are all written from these results.

The pack itself is one more row, with the two checks that concern files no task owns (an asset or suite that does
not load, a symlink out of the pack, the pack's total size).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dojo.compiler.asset_sanity import asset_sanity
from dojo.compiler.horizon import auto_horizon
from dojo.compiler.pack_audit import Finding, PackTask, file_problems, other_pack_files, own_assets
from dojo.compiler.pack_limits import PackLimits, pack_safety, task_safety
from dojo.compiler.spec_library import SpecLibrary

from dojo.experts.validity import SUCCESS_BAR
from dojo.strict.work import EpisodeRecord, PlanRecord

REDRAW_WARNING = 0.10
"""Share of seeds whose first layout was redrawn above which stability warns (the layouts are fragile)."""
REST_DRIFT_MM = 5.0
"""How far (mm) an object may move in the second after the compiled initial state and still be at rest."""

STATUSES = ("pass", "warn", "fail", "skip")


@dataclass(frozen=True)
class CheckResult:
    """What one check concluded for one row: `pass`, `warn` (passed, with warnings), `fail` or `skip` (not run:
    an earlier check failed, or it does not apply)."""

    check: str
    status: str
    figure: str
    findings: tuple[Finding, ...] = ()
    seconds: float = 0.0


@dataclass
class Audit:
    """One row of the report: a task of a pack (`task`), or the pack itself (`task` None), and what was gathered
    for it: plans compiled twice (`plans`, every protocol setting x seed) and episodes by policy."""

    pack: Path
    name: str
    file: str
    task: PackTask | None = None
    plans: list[PlanRecord] | None = None
    episodes: dict[str, list[EpisodeRecord]] = field(default_factory=dict)
    results: list[CheckResult] = field(default_factory=list)

    @property
    def failed(self) -> bool:
        return any(r.status == "fail" for r in self.results)


@dataclass(frozen=True)
class Context:
    """What every check may read besides its row."""

    library: SpecLibrary
    limits: PackLimits
    seeds: int


@dataclass(frozen=True)
class Check:
    """One check: its name (the report's and JUnit's), what passing it proves, the work it needs gathered first
    (None; `plans`; `expert`; `floor` for zero and random) and how it judges a row."""

    name: str
    proves: str
    needs: str | None
    run: Callable[[Audit, Context], CheckResult]


def _result(name: str, figure: str, findings: list[Finding]) -> CheckResult:
    errors = any(not f.warning for f in findings)
    status = "fail" if errors else "warn" if findings else "pass"
    return CheckResult(name, status, figure, tuple(findings))


def _problems(items: list) -> list[Finding]:
    return [Finding(str(p)) for p in items]


# ---- task checks ---------------------------------------------------------------------------------------------


def _schema(audit: Audit, ctx: Context) -> CheckResult:
    assert audit.task is not None
    if file_problems(ctx.library, audit.task.file, safety=True):  # an unsafe file is judged by safety alone
        return CheckResult("schema", "skip", "not judged: the file breaks the safety rules (see safety)")
    problems = file_problems(ctx.library, audit.task.file, safety=False)
    return _result("schema", f"{len(problems)} problem(s)" if problems else "valid, references resolve",
                   _problems(problems))


def _safety(audit: Audit, ctx: Context) -> CheckResult:
    assert audit.task is not None
    findings = _problems(file_problems(ctx.library, audit.task.file, safety=True))
    if findings or audit.task.spec is None:
        return _result("safety", "the loader refused the file", findings)
    figure, more = task_safety(ctx.library, audit.task.spec, own_assets(ctx.library, audit.task.spec), ctx.limits)
    return _result("safety", figure, more)


def _assets(audit: Audit, ctx: Context) -> CheckResult:
    assert audit.task is not None and audit.task.spec is not None
    assets = own_assets(ctx.library, audit.task.spec)
    findings: list[Finding] = []
    densities: list[float] = []
    largest, meshes = 0.0, 0
    for asset in assets:
        figures, found = asset_sanity(asset)
        findings += found
        if figures:
            densities += figures.densities
            largest, meshes = max(largest, figures.largest), meshes + figures.meshes
    if not assets:
        return CheckResult("asset", "pass", "no assets of its own (built-in ones only)")
    figure = f"{len(assets)} asset(s), {meshes} collision mesh(es), largest {largest:.2f} m"
    if densities:
        low, high = (f"{d:,.3g}" for d in (min(densities), max(densities)))
        figure += f", {low if low == high else low + '-' + high} kg/m^3"
    return _result("asset", figure, findings)


def _determinism(audit: Audit, ctx: Context) -> CheckResult:
    plans = audit.plans or []
    findings = [Finding(f"{p.setting} seed {p.seed} does not compile: {p.error}") for p in plans
                if p.error and not p.layout]
    findings += [Finding(f"{p.setting} seed {p.seed}: compiling it again changed {', '.join(p.differs)}")
                 for p in plans if p.differs]
    compiled = [p for p in plans if not p.error]
    figure = f"{len(compiled)} plan(s) compiled twice: " + ("identical" if not findings else
                                                            f"{len(findings)} differ or fail")
    unsettled = len([p for p in plans if p.layout])
    if unsettled:
        figure += f" ({unsettled} did not settle: see stability)"
    return _result("determinism", figure, findings)


def _stability(audit: Audit, ctx: Context) -> CheckResult:
    plans = audit.plans or []
    findings = [Finding(f"{p.setting} seed {p.seed}: {p.error}") for p in plans if p.layout]
    settled = [p for p in plans if not p.error]
    findings += [Finding(f"{p.setting} seed {p.seed}: {p.drift_object} moved {p.drift_mm:.1f} mm in the first "
                         f"second with the robot at home (at most {REST_DRIFT_MM:g} mm): the scene is not at rest")
                 for p in settled if p.drift_mm > REST_DRIFT_MM]
    redrawn = [p for p in settled if p.redraws]
    share = len(redrawn) / len(plans) if plans else 0.0
    if share > REDRAW_WARNING:
        seeds = ", ".join(f"{p.setting} {p.seed} ({p.redraws}x)" for p in redrawn)
        findings.append(Finding(f"{len(redrawn)} of {len(plans)} scenes ({100 * share:.0f}%) needed their layout "
                                f"redrawn to settle (above {100 * REDRAW_WARNING:.0f}%): {seeds}; objects land on "
                                "each other or tip over: give them more room", warning=True))
    figure = f"{len(settled)}/{len(plans)} scenes settled"
    if settled:
        figure += f" (drift <= {max(p.drift_mm for p in settled):.1f} mm in 1 s)"
    figure += f", redrawn on {len(redrawn)} ({100 * share:.0f}%)"
    return _result("stability", figure, findings)


def _rate(episodes: list[EpisodeRecord]) -> tuple[int, int]:
    return sum(e.success for e in episodes), len(episodes)


def _episode_text(e: EpisodeRecord) -> str:
    return f"{e.setting} {e.seed}" + (f" ({e.error})" if e.error else f" (score {e.score:.0f}, {e.steps} steps)")


def has_expert(audit: Audit) -> bool:
    """Whether the row's task declares a scripted expert (only those have expert episodes to judge)."""
    return audit.task is not None and audit.task.spec is not None and bool(audit.task.spec.data.get("expert"))


def _without_expert(name: str, audit: Audit) -> CheckResult:
    """Solvability or horizon of a task with no scripted expert: not judged when raters score it (a real-world
    task, whose emulator scene only approximates the objects), else a failure: a simulated task must prove
    itself solvable."""
    assert audit.task is not None and audit.task.spec is not None
    if audit.task.spec.data.get("scored_by") == "raters":
        return CheckResult(name, "skip", "not judged: scored by raters, no scripted expert on the emulator")
    return _result(name, "no scripted expert", [Finding(
        "the task declares no `expert:`, so nothing shows it can be solved: add a scripted expert (a list of "
        "skills), or set `scored_by: raters` if people score it from videos (real-world tasks)")])


def _solvability(audit: Audit, ctx: Context) -> CheckResult:
    if not has_expert(audit):
        return _without_expert("solvability", audit)
    episodes = audit.episodes["expert"]
    wins, n = _rate(episodes)
    figure = f"expert {wins}/{n} ({100 * wins / n:.0f}%)"
    failed = [e for e in episodes if not e.success]
    if failed:
        figure += "; failed: " + ", ".join(f"{e.setting} {e.seed}" for e in failed)
    findings = []
    if wins < SUCCESS_BAR * n:
        findings.append(Finding(f"the scripted expert succeeds on {wins} of {n} seeds, below "
                                f"{100 * SUCCESS_BAR:.0f}%; failed: {', '.join(map(_episode_text, failed))}"))
    return _result("solvability", figure, findings)


def _not_trivial(audit: Audit, ctx: Context) -> CheckResult:
    findings = []
    parts = []
    for name in ("zero", "random"):
        episodes = audit.episodes[name]
        wins, n = _rate(episodes)
        score = float(np.mean([e.score for e in episodes])) if episodes else 0.0
        parts.append(f"{name} {wins}/{n} (score {score:.1f})")
        if wins:
            seeds = ", ".join(f"{e.setting} {e.seed}" for e in episodes if e.success)
            what = "doing nothing" if name == "zero" else "random motion"
            findings.append(Finding(f"the {name} policy succeeds on {wins} of {n} seeds ({seeds}): the task is "
                                    f"solved by {what}; is the success condition true at the start?"))
        elif name == "zero" and score > 0:
            findings.append(Finding(f"the zero policy scores {score:.1f} on average: the task gives credit for doing "
                                    "nothing (a stage that holds at the start?)", warning=True))
    return _result("not_trivial", ", ".join(parts), findings)


def _horizon(audit: Audit, ctx: Context) -> CheckResult:
    if not has_expert(audit):
        return _without_expert("horizon", audit)
    lengths = [e.steps for e in audit.episodes["expert"] if e.success]
    horizon = max(p.horizon for p in audit.plans or [] if not p.error)
    need = auto_horizon(lengths)
    p90 = float(np.percentile(lengths, 90))
    figure = f"expert p90 {p90:.0f} steps x 1.2 = {need} <= horizon {horizon}"
    findings = []
    if need > horizon:
        figure = f"expert p90 {p90:.0f} steps x 1.2 = {need} > horizon {horizon}"
        findings.append(Finding(f"the expert's 90th-percentile episode ({p90:.0f} steps) with 20% margin needs "
                                f"{need} control steps, above the task's horizon of {horizon}: raise the horizon "
                                f"to at least {need}, or make the expert faster"))
    return _result("horizon", figure, findings)


TASK_CHECKS: tuple[Check, ...] = (
    Check("schema", "the task's spec is well-formed and its references resolve", None, _schema),
    Check("safety", "nothing in it runs code or reads outside the pack, and it stays within the limits", None,
          _safety),
    Check("asset", "its own assets load, collide with closed meshes, weigh plausibly and measure in metres", None,
          _assets),
    Check("determinism", "every (setting, seed) compiles, and twice to the same plan", "plans", _determinism),
    Check("stability", "every compiled scene settles and stays at rest", "plans", _stability),
    Check("solvability", f"the scripted expert succeeds on at least {100 * SUCCESS_BAR:.0f}% of the seeds",
          "expert", _solvability),
    Check("not_trivial", "zero and random never succeed, and zero scores nothing", "floor", _not_trivial),
    Check("horizon", "the expert's 90th-percentile length x 1.2 fits in the horizon", "expert", _horizon),
)


# ---- the pack row ---------------------------------------------------------------------------------------------


def _pack_schema(audit: Audit, ctx: Context) -> CheckResult:
    problems = [p for f in other_pack_files(ctx.library, audit.pack)
                for p in file_problems(ctx.library, f, safety=False)]
    return _result("schema", f"{len(problems)} problem(s) in its other specs" if problems else
                   "its other specs (assets, suites, taxonomies) are valid", _problems(problems))


def _pack_safety(audit: Audit, ctx: Context) -> CheckResult:
    findings = [Finding(str(p)) for f in other_pack_files(ctx.library, audit.pack)
                for p in file_problems(ctx.library, f, safety=True)]
    figure, more = pack_safety(audit.pack, ctx.limits)
    return _result("safety", f"{figure} in all, no link out of the pack" if not more else figure, findings + more)


PACK_CHECKS: tuple[Check, ...] = (
    Check("schema", "the pack's other specs are well-formed", None, _pack_schema),
    Check("safety", "no file of the pack runs code or leads out of it, and the pack is within its size limit",
          None, _pack_safety),
)
