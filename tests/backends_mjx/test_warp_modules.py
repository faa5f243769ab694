"""`dojo bench kernels` (`dojo.bench.warp_modules`): MuJoCo Warp's modules per bucket, recorded on Warp's CPU device
without compiling. Needs warp-lang, which the plain install leaves out (GPU machines have it)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys

import pytest
from conftest import toy_plan

from dojo.backends.mjx.bucket import make_buckets

HAS_WARP = importlib.util.find_spec("warp") is not None
needs_warp = pytest.mark.skipif(not HAS_WARP, reason="needs warp-lang")


@pytest.mark.skipif(HAS_WARP, reason="checks the message given where warp-lang is missing")
def test_without_warp_the_command_says_what_to_install(tmp_path):
    done = subprocess.run([sys.executable, "-m", "dojo.cli.main", "bench", "kernels", "tasks=[push_t]", "episodes=1"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert done.returncode != 0 and done.stdout == ""
    assert "dojo bench kernels needs warp-lang (pip install 'warp-lang>=1.19')" in done.stderr


@needs_warp
def test_modules_are_recorded_per_bucket_and_shared_ones_counted_once():
    from dojo.bench.warp_modules import bucket_modules, kernel_figures

    buckets = make_buckets([toy_plan(task="a"), toy_plan(task="b", items=("ball",))])
    assert len(buckets) == 2
    sets = [bucket_modules(b) for b in buckets]
    figures = kernel_figures(buckets)
    assert figures["modules"] == len(sets[0] | sets[1]) < len(sets[0]) + len(sets[1])
    assert figures["shared_by_every_bucket"] == len(sets[0] & sets[1]) > 0
    # the ball brings sphere pairs: a collision kernel of its own that the box-only scene does not launch
    ball = figures["per_bucket"][buckets[1].key]
    assert any(name.startswith("_primitive_narrowphase") for name in ball["own"]), ball["own"]
    assert set(ball["own"]) == sets[1] - sets[0]


@needs_warp
def test_recording_leaves_warp_as_it_was():
    import warp

    from dojo.bench.warp_modules import bucket_modules

    launch, capture_while, suggested = warp.launch, warp.capture_while, warp.get_suggested_block_size
    bucket_modules(make_buckets([toy_plan()])[0])
    assert warp.launch is launch and warp.capture_while is capture_while
    assert warp.get_suggested_block_size is suggested


@needs_warp
def test_a_kernel_whose_occupancy_is_asked_for_is_recorded_at_its_default_block_size_too():
    """On a GPU, `wp.get_suggested_block_size` loads the kernel's module at its default block size to ask the driver,
    and the N-squared broadphase then launches at its model's own (128): the GPU compiles both variants, so both are
    recorded, and compiled ahead. Without the first, an H200 compiled 10 broadphase modules of the protocol's run
    that the cache compiled ahead lacked (2026-12-03)."""
    from dojo.backends.mjx.warp_launches import recorded_tick

    launches, _ = recorded_tick(make_buckets([toy_plan(task="a"), toy_plan(task="b", items=("ball",))])[1], "cpu", 4)
    sizes = {size for name, size in launches if name.startswith("_nxn_broadphase")}
    assert None in sizes and len(sizes) == 2, sizes


@needs_warp
def test_buckets_rounded_to_one_dof_count_share_their_solver_kernels():
    from dojo.backends.mjx.dof_rounding import round_bucket
    from dojo.bench.warp_modules import kernel_figures

    buckets = make_buckets([toy_plan(task="a"), toy_plan(task="b", items=("ball",))])
    apart = kernel_figures(buckets)
    rounded = kernel_figures([round_bucket(b, 16) for b in buckets])
    assert rounded["modules"] < apart["modules"]
    jaref = "_solve_init_jaref_kernel"
    assert rounded["generated_kernels"][jaref] == 1 < apart["generated_kernels"][jaref]


@needs_warp
def test_a_lanes_tick_is_counted_in_launches_its_refresh_lighter_than_a_forward():
    """`recorded_tick`: a lane's tick is its sub-steps and its refresh (`streams.refresh`), which launches a
    fraction of a forward's kernels (no constraints, no solver) and more than none (poses, contacts)."""
    from dojo.bench.warp_modules import kernel_figures

    bucket = make_buckets([toy_plan()])[0]
    counts = kernel_figures([bucket])["per_bucket"][bucket.key]["launches"]
    assert counts["step"] > counts["forward"] > 2 * counts["refresh"] > 0
    assert counts["tick"] == bucket.n_substeps * counts["step"] + counts["refresh"]


@needs_warp
def test_the_modules_of_a_lanes_refresh_are_recorded_too():
    """An engine loads every module its lanes launch, the refresh's included: `stack_blocks`' grippers are tendons,
    whose speeds the refresh brings up to date with a kernel of our own (`lane_kernels`), which a step never
    launches. A cold start compiles it, so `dojo bench kernels` counts it and `arch=` compiles it."""
    from dojo.bench.warp_modules import bucket_modules
    from dojo.compiler.plan import compile_plan
    from dojo.compiler.spec_library import SpecLibrary

    library = SpecLibrary.load()
    bucket = make_buckets([compile_plan(library, library.get("task", "stack_blocks"), "standard", 0)])[0]
    assert any(name.startswith("dojo.backends.mjx.lane_kernels") for name in bucket_modules(bucket))


@needs_warp
def test_a_model_of_a_thousand_geoms_sorts_in_its_broadphase_and_is_recorded_all_the_same():
    """MuJoCo Warp sweeps and prunes where a model has 1,000 geoms or more (every robot's union merged with
    `backend.merge_growth=inf` did), sorting between launches with Warp's native sort; recorded, that sort read
    bounds no launch had filled and failed ("Warp sort error: Invalid segment range"). It is skipped now, and
    put back after."""
    import warp

    from dojo.bench.warp_modules import bucket_modules

    sort = warp.utils.segmented_sort_pairs
    bucket = make_buckets([toy_plan(clutter=("ball",) * 1000)])[0]
    assert bucket.model.ngeom >= 1000
    assert any(name.startswith("_sap_broadphase") for name in bucket_modules(bucket))
    assert warp.utils.segmented_sort_pairs is sort


@needs_warp
def test_the_kernels_are_those_of_the_plans_a_mjx_run_keeps_on_mjx():
    """`dojo bench kernels` buckets what `dojo run backend=mjx` gives the mjx backend: a task with scripted events
    runs on `mujoco` (`dojo.evaluation.routing`), so its plans bring no buckets and are counted apart."""
    from dojo.bench.warp_modules import bench_kernels, mjx_plans
    from dojo.bench.sim_bench import load_plans

    cfg = {"tasks": ["push_t", "insert_key"], "episodes": 1, "backend": {}}
    plans = load_plans(cfg)
    kept, elsewhere = mjx_plans(plans, {})
    assert [p.task for p in kept] == ["push_t"] and elsewhere == {"insert_key": 1}
    figures = bench_kernels(cfg)
    assert figures["tasks"] == ["push_t"] and figures["run_on_mujoco"] == {"insert_key": 1}
    assert figures["buckets"] == 1
    with pytest.raises(ValueError, match="no plan here runs on backend mjx"):
        mjx_plans([p for p in plans if p.task == "insert_key"], {})


@needs_warp
def test_a_bucket_is_recorded_as_a_lane_of_its_size_holds_it():
    """The modules recorded for a lane of 4 worlds are those the stream engine's own lane of 4 launches; one world
    would miss the variants MuJoCo Warp specialises on a batched field's rows (the broadphase of members whose geom
    bounds differ)."""
    import warp as wp

    from dojo.backends.mjx.streams import StreamEngine
    from dojo.backends.mjx.warp_launches import _recording, recorded_tick
    from dojo.bench.warp_modules import _module_names

    [bucket] = make_buckets([toy_plan(setting="random", seed=s, clutter=c)
                             for s, c in enumerate([("ball",), ("ball", "box")])])
    assert "geom_aabb" in bucket.varying
    engine = StreamEngine([bucket], [4], [[]], device="cpu")
    lane, launched = engine.lanes[0], {}
    with wp.ScopedDevice("cpu"), _recording(wp, launched):
        engine.mjw.step(lane.model, lane.data)
    as_lane, one = (_module_names(recorded_tick(bucket, "cpu", n)[0]) for n in (4, 1))
    assert _module_names(launched) <= as_lane
    missed = _module_names(launched) - one
    assert missed and all(name.startswith("_nxn_broadphase") for name in missed), missed


@needs_warp
def test_bench_kernels_sizes_lanes_as_the_run_would():
    from dojo.bench.warp_modules import bench_kernels

    figures = bench_kernels({"tasks": ["push_t"], "episodes": 2, "num_envs": 1, "backend": {"merge": False}})
    assert [b["worlds"] for b in figures["per_bucket"].values()] == [1] * figures["buckets"]
    figures = bench_kernels({"tasks": ["push_t"], "episodes": 2, "num_envs": 8, "backend": {"merge": False}})
    assert sum(b["worlds"] for b in figures["per_bucket"].values()) == figures["episodes"] == 2


def test_the_kernels_name_the_plans_compiler_and_warn_where_it_is_not_this_installs(tmp_path, caplog):
    """Kernels compiled ahead serve a GPU run only where it reuses the plans, so where its install is the one the
    plans are named by: the figures name it, and a folder of another install's plans is said to be one."""
    import json
    import logging

    from dojo.bench.warp_modules import plans_compiler
    from dojo.compiler.plan import compiler_id

    assert plans_compiler(None) == compiler_id()  # plans compiled by the bench itself
    assert plans_compiler(str(tmp_path)) is None  # plan files without an index: not known
    (tmp_path / "index.json").write_text(json.dumps({"compiler": compiler_id()}))
    with caplog.at_level(logging.WARNING):
        assert plans_compiler(str(tmp_path)) == compiler_id()
    assert not caplog.records
    other = compiler_id().replace("mujoco ", "mujoco 0.0.1-not-")
    (tmp_path / "index.json").write_text(json.dumps({"compiler": other}))
    with caplog.at_level(logging.WARNING):
        assert plans_compiler(str(tmp_path)) == other
    assert any(other in r.getMessage() and "compile the plans again" in r.getMessage() for r in caplog.records)
