"""The xpolicylab command line: help pages, exit code 2 with a suggestion, and serve + check end to end."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from xpolicylab.cli import bench_main, check_main, main, new_main, serve_main

from conftest import free_port, serving


@pytest.mark.parametrize("command", ["serve", "check", "new", "bench"])
def test_help_says_what_and_shows_an_example(command, capsys):
    assert main([command, "--help"]) == 0
    out = capsys.readouterr().out
    assert f"xpolicylab {command}" in out and "example:" in out


@pytest.mark.parametrize("argv,hint", [
    (["check", "urll=ws://x"], "'url'"),
    (["serve", "prot=openpi"], "'protocol'"),
    (["serve", "policy=zeroo"], "zero"),
    (["serve", "protocol=grpc"], "protocol"),
    (["check", "url=ws://x", "n=many"], "integer"),
    (["check", "n=3"], "url="),
    (["bench", "protocols=[http]"], "protocols"),
    (["chek"], "'check'"),
    (["new"], "NAME"),
    (["serve", "justaword"], "key=value"),
])
def test_bad_arguments_exit_2_with_a_clear_message(argv, hint, capsys):
    assert main(argv) == 2
    assert hint in capsys.readouterr().err


def test_entry_points_for_dojo_return_codes(capsys, tmp_path):
    assert serve_main(["nope=1"]) == 2
    assert bench_main(["batch=x"]) == 2
    assert new_main(["pkg", "--dir", str(tmp_path)]) == 0
    assert (tmp_path / "pkg" / "deploy.yml").is_file()
    with serving() as srv:
        assert check_main([f"url={srv.url}", "width=64", "height=48", "n=3"]) == 0
    assert "RESULT: PASS" in capsys.readouterr().out


def test_python_m_serve_then_check():
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "xpolicylab.serve", "policy=random", f"port={port}",
                             "protocol=openpi", "log_level=warning"], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().startswith("xpolicylab serving random (openpi) on ws://127.0.0.1:")
        check = subprocess.run([sys.executable, "-m", "xpolicylab.cli", "check", f"url=ws://127.0.0.1:{port}",
                                "protocol=openpi", "cameras=[head]", "width=64", "height=48", "n=3"],
                               capture_output=True, text=True, timeout=120)
        assert check.returncode == 0, check.stdout + check.stderr
        assert "RESULT: PASS" in check.stdout
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_bench_prints_one_json_line(capsys):
    assert bench_main(["batch=2", "width=32", "height=24", "n=2", "warmup=1", "single_n=2"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1
    figures = json.loads(lines[0])
    for protocol in ("xpolicylab", "openpi"):
        assert {"mb_per_s", "batch_rtt_ms_p50", "batch_rtt_ms_p99", "single_rtt_ms_p50"} <= figures[protocol].keys()


@pytest.mark.slow
def test_bench_full_size(capsys):
    """The issue's configuration: batch 64, three 640x480 images, both dialects (figures, not assertions)."""
    assert bench_main(["batch=64", "n=20"]) == 0
    print(capsys.readouterr().out)


def test_a_served_reference_policy_asks_for_the_cameras_it_is_given():
    """`cameras`, `width` and `height` make a zero policy ask for images (to exercise the image path end to end);
    by default it asks for none, at any size."""
    from xpolicylab.client import PolicyClient

    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "xpolicylab.serve", "policy=zero", f"port={port}",
                             "cameras=[head,left_wrist,right_wrist]", "width=224", "height=160",
                             "log_level=warning"], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().startswith("xpolicylab serving zero")
        with PolicyClient(f"ws://127.0.0.1:{port}") as client:
            meta = client.metadata
        assert meta.cameras == ("head", "left_wrist", "right_wrist")
        assert (meta.image_width, meta.image_height) == (224, 160)
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    with serving() as srv, PolicyClient(srv.url) as client:
        meta = client.metadata
        assert meta.cameras == () and meta.image_width is None
    assert serve_main(["width=0"]) == 2
