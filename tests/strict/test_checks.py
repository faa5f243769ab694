"""The simulated checks' judgement, on records made up to sit just either side of each bar (no simulation)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

from dojo.compiler.pack_limits import PackLimits
from dojo.strict.checks import TASK_CHECKS, Audit, Context
from dojo.strict.work import EpisodeRecord, PlanRecord

CHECK = {c.name: c for c in TASK_CHECKS}
CTX = Context(library=None, limits=PackLimits(), seeds=20)  # these checks read only their row


def _plan(seed: int, **fields) -> PlanRecord:
    return PlanRecord(**{"setting": "standard", "seed": seed, "hash": f"h{seed}", "path": f"p{seed}", "horizon": 400,
                         **fields})


def _episodes(policy: str, outcomes: list[tuple[bool, float, int]]) -> list[EpisodeRecord]:
    return [EpisodeRecord(policy, "standard", i, ok, score, steps) for i, (ok, score, steps) in enumerate(outcomes)]


def _task(**data) -> SimpleNamespace:
    """The part of a loaded task the checks read: its spec's data (a scripted expert unless told otherwise)."""
    return SimpleNamespace(spec=SimpleNamespace(data={"expert": [{"skill": "grasp", "object": "a"}], **data}))


def _judge(name: str, task: SimpleNamespace | None = None, **row) -> tuple[str, list[tuple[bool, str]]]:
    result = CHECK[name].run(Audit(Path("pack"), "t", "t.yaml", task or _task(), **row), CTX)
    return result.status, [(f.warning, f.message) for f in result.findings]


def test_determinism_names_what_changed_and_what_did_not_compile() -> None:
    assert _judge("determinism", plans=[_plan(i) for i in range(3)])[0] == "pass"
    status, findings = _judge("determinism", plans=[_plan(0), _plan(1, differs=("init_qpos", "model_xml")),
                                                    _plan(2, error="x.yaml:3:1: $.success: no joint 'lid/hinge'")])
    assert status == "fail" and [m for _, m in findings] == [
        "standard seed 2 does not compile: x.yaml:3:1: $.success: no joint 'lid/hinge'",
        "standard seed 1: compiling it again changed init_qpos, model_xml"]


def test_stability_fails_on_drift_and_warns_above_a_tenth_redrawn() -> None:
    calm = [_plan(i, redraws=1 if i < 2 else 0, drift_mm=0.3) for i in range(20)]  # 10% redrawn: no warning
    assert _judge("stability", plans=calm) == ("pass", [])
    fragile = [_plan(i, redraws=2 if i < 3 else 0) for i in range(20)]  # 15%
    status, findings = _judge("stability", plans=fragile)
    assert status == "warn" and findings[0][0] and "3 of 20 scenes (15%) needed their layout redrawn" in findings[0][1]
    moving = [_plan(0, drift_mm=5.1, drift_object="ball")] + [_plan(i) for i in range(1, 20)]
    status, findings = _judge("stability", plans=moving)
    assert status == "fail" and findings == [(False, "standard seed 0: ball moved 5.1 mm in the first second with "
                                                     "the robot at home (at most 5 mm): the scene is not at rest")]


def test_solvability_bar_is_95_percent() -> None:
    assert _judge("solvability", episodes={"expert": _episodes("expert", [(True, 100, 300)] * 19
                                                               + [(False, 50, 400)])})[0] == "pass"
    status, findings = _judge("solvability", episodes={"expert": _episodes("expert", [(True, 100, 300)] * 18
                                                                           + [(False, 50, 400)] * 2)})
    assert status == "fail" and "succeeds on 18 of 20 seeds, below 95%; failed: standard 18 (score 50, 400 steps)" \
        in findings[0][1]


def test_zero_credit_is_a_warning_and_any_floor_success_a_failure() -> None:
    nothing = _episodes("random", [(False, 0.0, 400)] * 4)
    status, findings = _judge("not_trivial", episodes={"zero": _episodes("zero", [(False, 50.0, 400)] * 4),
                                                       "random": nothing})
    assert status == "warn" and findings == [(True, "the zero policy scores 50.0 on average: the task gives credit "
                                                    "for doing nothing (a stage that holds at the start?)")]
    status, _ = _judge("not_trivial", episodes={"zero": _episodes("zero", [(False, 0.0, 400)] * 4),
                                                "random": _episodes("random", [(True, 100.0, 37)] + [(False, 0, 400)] * 3)})
    assert status == "fail"


def test_a_task_without_an_expert_fails_solvability_unless_raters_score_it() -> None:
    for name in ("solvability", "horizon"):
        status, findings = _judge(name, _task(expert=None), plans=[_plan(0)], episodes={"expert": []})
        assert status == "fail" and "declares no `expert:`" in findings[0][1]
        assert _judge(name, _task(expert=None, scored_by="raters"), plans=[_plan(0)],
                      episodes={"expert": []}) == ("skip", [])
    ok = _episodes("expert", [(False, 0, 300)] * 20)  # raters do not excuse an expert that is there and fails
    assert _judge("solvability", _task(scored_by="raters"), episodes={"expert": ok})[0] == "fail"


def test_horizon_needs_the_p90_with_a_fifth_to_spare() -> None:
    fits = _episodes("expert", [(True, 100, 300)] * 9 + [(True, 100, 333)])  # p90 = 303.3 -> 364
    assert _judge("horizon", plans=[_plan(0)], episodes={"expert": fits})[0] == "pass"
    long = _episodes("expert", [(True, 100, 340)] * 10)  # 340 x 1.2 = 408 > 400
    status, findings = _judge("horizon", plans=[_plan(0)], episodes={"expert": long})
    assert status == "fail" and "raise the horizon to at least 408" in findings[0][1]
