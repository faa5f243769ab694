"""`kernel_cache.compile_ahead`: Warp modules compiled for a GPU architecture on a machine without one, under the
names a GPU machine's `Module.load` looks for. Needs warp-lang (its CUDA compiler, NVRTC, runs without a GPU)."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.skipif(importlib.util.find_spec("warp") is None, reason="needs warp-lang")

KERNELS = textwrap.dedent('''
    import warp as wp

    @wp.kernel
    def scale(x: wp.array(dtype=float), s: float):
        i = wp.tid()
        x[i] = x[i] * s
''')


def _module(tmp_path, name: str):
    """A Python module of one Warp kernel, imported fresh: a Warp module whose compile takes a second."""
    (tmp_path / f"{name}.py").write_text(KERNELS)
    sys.path.insert(0, str(tmp_path))
    try:
        return importlib.import_module(name).scale.module
    finally:
        sys.path.remove(str(tmp_path))


@pytest.fixture
def warp_cache(tmp_path):
    """Warp's kernel cache moved to an empty folder for the test, and back afterwards."""
    import warp as wp

    wp.init()
    kept = wp.config.kernel_cache_dir
    wp.config.kernel_cache_dir = str(tmp_path / "cache")
    yield tmp_path / "cache"
    wp.config.kernel_cache_dir = kept


def test_modules_compile_for_a_gpu_arch_where_warps_own_aot_compile_puts_them_and_only_once(tmp_path, warp_cache):
    import warp as wp

    from dojo.backends.mjx.kernel_cache import compile_ahead

    module = _module(tmp_path, "aot_kernels_a")
    first = compile_ahead({(module.name, None): module}, arch=90)
    assert (first["modules"], first["compiled"], first["cached"]) == (1, 1, 0)
    assert first["arch"] == "sm_90" and first["bytes"] > 0
    # Warp's public ahead-of-time compile, into a folder of its own, names the same CUBIN: the file a device of
    # sm_90 loads (Module.load: <cache>/<module id>/<file>) when its driver predates Warp's toolkit
    theirs = wp.compile_aot_module(module, arch=90, module_dir=tmp_path / "theirs", use_ptx=False)
    ident = module.get_module_identifier(module.options["block_dim"])
    ours = warp_cache / ident / os.path.basename(theirs[0])
    assert os.path.basename(theirs[0]).endswith(".sm90.cubin") and ours.is_file()
    assert (warp_cache / ident / f"{ident}.meta").is_file()
    again = compile_ahead({(module.name, None): module}, arch=90)
    assert (again["compiled"], again["cached"]) == (0, 1)


def test_each_block_size_a_module_is_launched_with_is_its_own_compiled_variant(tmp_path, warp_cache):
    from dojo.backends.mjx.kernel_cache import compile_ahead

    module = _module(tmp_path, "aot_kernels_b")
    out = compile_ahead({(module.name, None): module, (module.name, 64): module}, arch=90, jobs=2)
    assert (out["modules"], out["compiled"]) == (2, 2)
    assert module.get_module_identifier(64) != module.get_module_identifier(module.options["block_dim"])
    assert (warp_cache / module.get_module_identifier(64)).is_dir()


def test_dojo_bench_kernels_with_arch_says_so_in_its_figures(tmp_path):
    """The command's JSON line carries `ahead` only when asked (`arch=`), so a count stays a count."""
    done = subprocess.run([sys.executable, "-m", "dojo.cli.main", "bench", "kernels", "tasks=[push_t]", "episodes=1",
                           "arch=null"], cwd=tmp_path, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "WARP_CACHE_PATH": str(tmp_path / "cache")})
    assert done.returncode == 0, done.stderr
    assert '"ahead"' not in done.stdout and '"modules"' in done.stdout


def test_what_a_step_compiled_is_the_difference_of_two_readings_of_the_cache(tmp_path, warp_cache, caplog):
    """`MjxBackend.load` says how many Warp modules its set-up compiled rather than found (`cached_binaries`)."""
    import logging

    from dojo.backends.mjx.backend import MjxBackend
    from dojo.backends.mjx.kernel_cache import cached_binaries, compile_ahead

    module = _module(tmp_path, "aot_kernels_c")
    before = cached_binaries()
    compile_ahead({(module.name, None): module}, arch=90)
    (warp_cache / "sources").mkdir()
    (warp_cache / "sources" / "kernel.cu").write_text("")  # a module's sources and metadata are not a compile
    [new] = cached_binaries() - before
    assert new.endswith(".sm90.cubin") and new.startswith(module.get_module_identifier(module.options["block_dim"]))
    with caplog.at_level(logging.INFO, logger="dojo.backends.mjx.backend"):
        MjxBackend._say_compiled(3)
        MjxBackend._say_compiled(0)
    assert f"Warp compiled 3 module(s) here during set-up, not found in its kernel cache ({warp_cache}" in caplog.text
    assert f"Warp found every module of the set-up in its kernel cache ({warp_cache})" in caplog.text
