"""Reports: JSON content, HTML safety and self-containment, `dojo report` arguments, and the page in Chromium."""

from __future__ import annotations

import json
import shutil
import subprocess
import tempfile
from html.parser import HTMLParser

import pytest

from dojo.compiler.taxonomy import builtin_taxonomy
from dojo.report.make_report import build_report, load_rows, render_html, report_main, write_report
from dojo.evaluation.results_store import STORE_FILENAME, ResultsStore
from dojo.report.scoring import score_episodes

DIMENSIONS = builtin_taxonomy().scored

EVIL = "<script>alert('x')</script>&\"quote\""


@pytest.fixture
def runs(tmp_path, make_task_rows):
    """Two run folders: a full policy with a hidden set (3 seeds), and a partial one with hostile strings."""
    good, evil = tmp_path / "runs" / "good", tmp_path / "runs" / "evil"
    with ResultsStore(good / STORE_FILENAME) as store:
        for seed in range(3):
            for d_index, dimension in enumerate(DIMENSIONS):
                for t in range(2):
                    wins = (seed + d_index + t) % 4  # 0..3 successes of 4
                    outcomes = [(i < wins, 100.0 if i < wins else 25.0 * i) for i in range(4)]
                    settings = ("standard", "random") if dimension == "generalization" else ("standard",)
                    for s_index, setting in enumerate(settings):
                        for row in make_task_rows(f"{dimension}_task{t}", dimension, outcomes, run_id="good-1",
                                                  eval_seed=seed, setting=setting, policy_name="Good Policy",
                                                  first_episode=10 * s_index,
                                                  video_path=f"videos/{dimension}_{t}_{seed}.mp4"):
                            store.add(row)
            for row in make_task_rows("precision_task0", "precision", [(True, 100.0), (False, 0.0)] * 4,
                                      run_id="good-1", eval_seed=seed, split="hidden", policy_name="Good Policy",
                                      first_episode=100, plan_hash="secret-hidden-plan",
                                      video_path="videos/secret-hidden.mp4"):
                store.add(row)
    with ResultsStore(evil / STORE_FILENAME) as store:
        for row in make_task_rows(EVIL, "memory", [(False, 10.0), (True, 100.0)], run_id="evil-1",
                                  policy_name=EVIL, failure_reason=EVIL, video_path="javascript:alert(1)",
                                  policy_meta={"note": EVIL}):
            store.add(row)
    return good, evil


def test_json_report_scores_and_leaderboard_order(runs, tmp_path):
    good, evil = runs
    report = write_report([good, evil], tmp_path / "out" / "r.json", tmp_path / "out" / "r.html")
    on_disk = json.loads((tmp_path / "out" / "r.json").read_text())
    assert on_disk["entries"][0]["policy"] == "Good Policy"  # complete entries rank before partial ones
    assert [e["policy"] for e in on_disk["entries"]] == ["Good Policy", EVIL]
    assert on_disk == json.loads(json.dumps(report))

    good_entry, evil_entry = report["entries"]
    with ResultsStore(good / STORE_FILENAME, readonly=True) as store:
        expected = score_episodes(store.rows())
    assert good_entry["scores"]["overall"]["score"]["mean"] == pytest.approx(expected.overall.score.mean)
    assert len(good_entry["scores"]["replicates"]) == 3
    assert good_entry["scores"]["generalization"] is not None
    # 8 hidden successes of 24 vs public: the verdict is computed and named.
    assert good_entry["verification"]["hidden_episodes"] == 24
    assert good_entry["verification"]["verdict"] in ("verified", "unverified")
    # The evil policy: one Memory task, 1 of 2 episodes succeeded, score (10 + 100) / 2.
    assert evil_entry["scores"]["partial"] is True
    assert evil_entry["scores"]["overall"]["success"]["mean"] == pytest.approx(50.0)
    assert evil_entry["scores"]["overall"]["score"]["mean"] == pytest.approx(55.0)
    assert evil_entry["verification"]["verdict"] == "not_evaluated"


def test_hidden_layouts_stay_private(runs, tmp_path):
    write_report(list(runs), tmp_path / "r.json", tmp_path / "r.html")
    for path in (tmp_path / "r.json", tmp_path / "r.html"):
        text = path.read_text()
        assert "secret-hidden" not in text


def test_html_is_self_contained_and_escaped(runs, tmp_path):
    write_report(list(runs), tmp_path / "out" / "r.json", tmp_path / "out" / "r.html")
    page = (tmp_path / "out" / "r.html").read_text()
    lowered = page.lower()
    assert "<script" not in lowered
    assert 'href="javascript' not in lowered  # a hostile video path is shown as text, never linked
    assert "(javascript:alert(1))" in page
    assert "&lt;script&gt;" in page
    for external in ("<link", " src=", "http://", "https://", "@import", "url("):
        assert external not in lowered.replace('xmlns="http://www.w3.org/2000/svg"', ""), external
    assert "Content-Security-Policy" in page
    # Relative video paths are resolved against the run folder, and linked relative to the page.
    assert 'href="../runs/good/videos/generalization_0_0.mp4"' in page


class _Elements(HTMLParser):
    """Counts elements and collects text, enough to check a page's structure."""

    def __init__(self) -> None:
        super().__init__()
        self.stack: list[str] = []
        self.counts: dict[str, int] = {}
        self.leaderboard_rows = 0
        self.text: list[str] = []
        self._in_leaderboard_body = False

    def handle_starttag(self, tag, attrs):
        self.counts[tag] = self.counts.get(tag, 0) + 1
        attributes = dict(attrs)
        if tag == "table" and "leaderboard" in (attributes.get("class") or ""):
            self._in_leaderboard_body = True
        if tag == "tr" and self._in_leaderboard_body and "tbody" in self.stack:
            self.leaderboard_rows += 1
        if tag == "svg":
            key = "svg." + (attributes.get("class") or "")
            self.counts[key] = self.counts.get(key, 0) + 1
        if tag not in ("br", "meta", "rect", "line", "path"):
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if tag == "table":
            self._in_leaderboard_body = False
        if tag in self.stack:
            while self.stack and self.stack.pop() != tag:
                pass

    def handle_data(self, data):
        self.text.append(data)


def test_page_structure(runs, tmp_path):
    report = build_report(load_rows(runs), runs)
    parsed = _Elements()
    parsed.feed(render_html(report, html_dir=tmp_path))
    assert parsed.leaderboard_rows == 2
    assert parsed.counts.get("svg.chart", 0) == 3  # score and success by dimension, standard vs random
    assert parsed.counts.get("svg.chart histogram", 0) == 2
    assert EVIL in "".join(parsed.text)  # shown verbatim, as text


def test_report_main_writes_both_files(runs, tmp_path, capsys):
    out = tmp_path / "reports"
    assert report_main([str(runs[0]), str(runs[1] / STORE_FILENAME), f"out={out}"]) == 0
    assert (out / "report.json").is_file() and (out / "report.html").is_file()
    printed = capsys.readouterr().out
    assert "Good Policy: score" in printed and "(partial)" in printed


def test_report_main_run_id_filter(runs, tmp_path):
    out = tmp_path / "only-good"
    assert report_main([str(runs[0]), str(runs[1]), "--run-id", "good-1", "--out", str(out)]) == 0
    entries = json.loads((out / "report.json").read_text())["entries"]
    assert [e["policy"] for e in entries] == ["Good Policy"]


def test_report_main_help_has_an_example(capsys):
    assert report_main(["--help"]) == 0
    assert "example:" in capsys.readouterr().out


def test_report_main_bad_input_is_a_message_not_a_traceback(tmp_path, capsys):
    assert report_main([]) == 2
    assert "dojo report:" in capsys.readouterr().err
    assert report_main([str(tmp_path / "missing"), f"out={tmp_path}"]) == 2
    err = capsys.readouterr().err
    assert "no results store" in err and "Traceback" not in err
    garbage = tmp_path / "garbage.sqlite"
    garbage.write_text("not sqlite at all " * 50)
    assert report_main([str(garbage), f"out={tmp_path}"]) == 2
    assert "not a usable" in capsys.readouterr().err
    ResultsStore(tmp_path / "empty" / STORE_FILENAME).close()
    assert report_main([str(tmp_path / "empty"), f"out={tmp_path / 'o'}"]) == 1
    assert "no episodes" in capsys.readouterr().err


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (apt-get install -y chromium; setup.sh does)")
def test_page_renders_in_headless_chromium(runs, tmp_path):
    html_path = tmp_path / "out" / "report.html"
    write_report(list(runs), tmp_path / "out" / "report.json", html_path)
    with tempfile.TemporaryDirectory() as profile:
        result = subprocess.run(
            [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             f"--user-data-dir={profile}", "--dump-dom", html_path.resolve().as_uri()],
            capture_output=True, text=True, timeout=120, check=False,
        )
    assert result.returncode == 0, result.stderr[-2000:]
    dom = _Elements()
    dom.feed(result.stdout)
    assert dom.counts.get("script", 0) == 0
    assert dom.leaderboard_rows == 2
    assert dom.counts.get("svg.chart", 0) == 3
    assert dom.counts.get("svg.chart histogram", 0) == 2
    assert dom.counts.get("rect", 0) > 20  # the bars are there
    text = " ".join(dom.text)
    for expected in ("Leaderboard", "Generalization", "Long-Horizon", "Good Policy", "standard vs random", EVIL):
        assert expected in text


def test_entries_on_different_plans_are_flagged(runs, tmp_path):
    report = write_report(list(runs), tmp_path / "r.json", tmp_path / "r.html")
    assert report["notes"] and "not evaluated on the same public plans" in report["notes"][0]
    alone = write_report([runs[0]], tmp_path / "a.json", tmp_path / "a.html")
    assert alone["notes"] == []


def _full_run(store_path, make_task_rows, policy: str, run_id: str, success: bool, meta: dict) -> None:
    """A run with one task of every dimension, all episodes `success`."""
    with ResultsStore(store_path) as store:
        for dimension in DIMENSIONS:
            for row in make_task_rows(f"{dimension}_task", dimension, [(success, 100.0 if success else 10.0)] * 2,
                                      run_id=run_id, policy_name=policy, policy_meta=meta):
                store.add(row)


def test_a_privileged_reference_is_marked_and_never_ranked(tmp_path, make_task_rows, capsys):
    """The scripted oracle scores 100: the report shows it for scale, after the ranked policies, marked."""
    runs = tmp_path / "outputs" / "suite"
    _full_run(runs / "oracle" / "default" / STORE_FILENAME, make_task_rows, "oracle", "o-1", True,
              {"name": "oracle", "extra": {"privileged": True}})
    _full_run(runs / "mine" / "default" / STORE_FILENAME, make_task_rows, "mine", "m-1", False, {"name": "mine"})
    assert report_main([str(runs / "oracle"), str(runs / "mine"), f"out={tmp_path / 'board'}"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("mine: score 10.00") and "privileged" not in lines[0]
    assert lines[1].startswith("oracle: score 100.00")
    assert lines[1].endswith("[privileged reference: reads the simulator state, not a leaderboard entry]")
    report = json.loads((tmp_path / "board" / "report.json").read_text())
    assert [(e["policy"], e["privileged"]) for e in report["entries"]] == [("mine", False), ("oracle", True)]
    page = (tmp_path / "board" / "report.html").read_text()
    board = page[page.index('<table class="leaderboard"'):page.index("</table>")]
    rows = board.split("<tr>")[2:]
    assert rows[0].startswith('<td class="num">1</td>') and "mine" in rows[0]
    assert rows[1].startswith('<td class="num">—</td>') and "b-privileged" in rows[1]


def test_a_folder_of_runs_is_every_store_below_it(tmp_path, make_task_rows, capsys):
    """`dojo report outputs/<suite>/<policy>` reads each run of that policy (one folder per run key)."""
    policy = tmp_path / "outputs" / "suite" / "zero"
    _full_run(policy / "default" / STORE_FILENAME, make_task_rows, "zero", "z-1", False, {})
    _full_run(policy / "episodes=1" / STORE_FILENAME, make_task_rows, "zero", "z-2", False, {})
    assert report_main([str(policy), f"out={tmp_path / 'r'}"]) == 0
    assert "(2 run(s) of 1 policies)" in capsys.readouterr().out
    assert report_main([str(tmp_path / "outputs" / "nothing-here"), f"out={tmp_path / 'r'}"]) == 2
    (tmp_path / "outputs" / "empty").mkdir()
    assert report_main([str(tmp_path / "outputs" / "empty"), f"out={tmp_path / 'r'}"]) == 2
    assert "no results store in" in capsys.readouterr().err


def test_the_default_report_folder_is_under_the_results_root(tmp_path, make_task_rows, monkeypatch):
    _full_run(tmp_path / "run" / STORE_FILENAME, make_task_rows, "p", "p-1", False, {})
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("DOJO_OUTPUTS", raising=False)
    assert report_main(["run"]) == 0
    assert (tmp_path / "outputs" / "report" / "report.html").is_file()
    monkeypatch.setenv("DOJO_OUTPUTS", str(tmp_path / "elsewhere"))
    assert report_main(["run"]) == 0
    assert (tmp_path / "elsewhere" / "report" / "report.json").is_file()
