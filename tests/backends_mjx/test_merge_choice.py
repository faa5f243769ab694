"""`backend.merge=auto` (the default): buckets merged across tasks where the physics is on streams and the run has
few environments per task and setting, at `AUTO_GROWTH`; as set otherwise."""

from __future__ import annotations

import logging

import pytest
from conftest import toy_plan

from dojo.backends.mjx.merge_groups import AUTO_BELOW, AUTO_GROWTH, GROWTH, choose_merge


def test_auto_merges_on_streams_where_few_environments_share_a_task_and_setting() -> None:
    # the protocol's run on a GPU: 850 environments in 20 (task, setting) groups, physics on streams
    merged, growth, why = choose_merge("auto", None, True, 850, 20)
    assert (merged, growth) == (True, AUTO_GROWTH) and "42.5 environments per task and setting" in why
    assert choose_merge("auto", None, True, AUTO_BELOW - 1, 1)[:2] == (True, AUTO_GROWTH)
    assert choose_merge("auto", None, True, AUTO_BELOW, 1)[:2] == (False, GROWTH)  # the bound itself: not merged
    assert choose_merge("auto", None, True, 16384, 42)[:2] == (False, GROWTH)  # a full GPU: separate buckets
    off, growth, why = choose_merge("auto", None, False, 850, 34)  # the jitted tick: not measured merged, not merged
    assert (off, growth) == (False, GROWTH) and "not on streams" in why
    assert choose_merge("auto", 0.25, True, 850, 34)[:2] == (True, 0.25)  # a growth that is set is kept
    assert choose_merge("auto", 0.25, True, 16384, 42)[:2] == (False, 0.25)  # also for the padding alone


def test_a_merge_that_is_set_is_kept_whatever_the_run() -> None:
    assert choose_merge(True, None, False, 16384, 1) == (True, GROWTH, "as set")
    assert choose_merge(False, None, True, 1, 34) == (False, GROWTH, "as set")
    assert choose_merge(True, float("inf"), True, 1, 1)[1] == float("inf")


def test_the_config_reaches_the_backend_and_a_bad_merge_setting_is_refused_by_name() -> None:
    from dojo.backends.registry import BackendOptions, make_backend

    backend = make_backend("mjx", BackendOptions(settings={}))
    assert (backend.merge, backend.merge_growth) == ("auto", None)
    backend = make_backend("mjx", BackendOptions(settings={"merge": None, "merge_growth": float("inf")}))
    assert (backend.merge, backend.merge_growth) == ("auto", float("inf"))
    with pytest.raises(ValueError, match="backend.merge takes true, false or auto, not 'often'"):
        make_backend("mjx", BackendOptions(settings={"merge": "often"}))


@pytest.mark.parametrize("streams, merged", [(True, True), (False, False)])
def test_load_buckets_the_plans_as_auto_decides_and_says_why(monkeypatch, caplog, streams, merged) -> None:
    """Three tasks, one environment each: merged at `AUTO_GROWTH` on streams, kept apart at `GROWTH` off them."""
    from dojo.backends.mjx import backend as backend_module
    from dojo.backends.mjx.backend import MjxBackend

    asked = []

    def bucketing(plans, merge, growth):
        asked.append((len(plans), merge, growth))
        raise InterruptedError  # the decision is what is tested: no engine is built

    monkeypatch.setattr(backend_module, "cached_buckets", bucketing)
    backend = MjxBackend(impl="jax", merge="auto")
    backend.streams = streams  # as `choose_streams` leaves it for MuJoCo Warp on a GPU, or off one
    plans = [toy_plan(task=task, seed=0) for task in ("toy", "pair", "twin")]
    with caplog.at_level(logging.INFO, logger="dojo.backends.mjx.backend"), pytest.raises(InterruptedError):
        backend.load(plans)
    assert asked == [(3, merged, AUTO_GROWTH if merged else GROWTH)] and backend.merged is merged
    said = "merged across tasks, growth 1" if merged else "not merged across tasks"
    assert f"mjx backend: buckets {said} (backend.merge=auto: " in caplog.text


def test_a_bad_merge_or_streams_setting_stops_a_run_before_any_backend_is_built(monkeypatch) -> None:
    """`registry.check_settings` through the run's factory: the loop builds its backend only when it has work,
    after the run has started, so a typo is refused where the factory is made."""
    from dojo.backends import mjx
    from dojo.backends.registry import factory_from_config

    monkeypatch.setattr(mjx, "make", lambda options: pytest.fail("no backend may be built"))
    refused = {"merge": ("often", "backend.merge takes true, false or auto, not 'often'"),
               "streams": ("maybe", "backend.streams takes true, false or auto, not 'maybe'"),
               "merge_growth": ("big", "backend.merge_growth takes a number of at least 0 or null, not 'big'")}
    for key, (value, message) in refused.items():
        with pytest.raises(ValueError, match=message):
            factory_from_config({"name": "mjx", key: value})
    with pytest.raises(ValueError, match="at least 0 or null, not -1$"):
        factory_from_config({"name": "mjx", "merge_growth": -1})
    factory_from_config({"name": "mjx", "merge": None, "streams": "auto", "merge_growth": float("inf")})
