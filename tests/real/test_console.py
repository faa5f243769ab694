"""The RealEval operator console end to end, in headless Chromium (Debian's, driven by Playwright) against the
emulated PiPER: log in with the token, reset the scene and record its layout, start a trial, e-stop it with the
keyboard (through the e-stop's own process, which answers 401 without the operator's token), see the arms return
to the reset pose in the emulator's own state, find the trial's video, and have three raters, each logged in with
their own token, score it blind (a planted disagreement is flagged; an appeal is recorded). Without a valid token
every page and the socket answer 401; a rater's token on an operator page or the socket answers 403, and the
operator's token does not score. A screenshot of each step is written to <results root>/figures/console/.
"""

from __future__ import annotations

import shutil
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("can")
pytest.importorskip("piper_sdk")
pytest.importorskip("fastapi")
uvicorn = pytest.importorskip("uvicorn")
sync_api = pytest.importorskip("playwright.sync_api")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (setup.sh installs it)")

import httpx  # noqa: E402
from websockets.exceptions import InvalidStatus  # noqa: E402
from websockets.sync.client import connect  # noqa: E402

from dojo.evaluation.results_store import ResultsStore  # noqa: E402
from dojo.evaluation.run_dir import results_root  # noqa: E402
from dojo.realeval.app import COOKIE, create_app  # noqa: E402
from dojo.realeval.cli import build_session, console_config  # noqa: E402
from dojo.realeval.raters import RaterRegistry  # noqa: E402

PACK = Path(__file__).parent / "pack"
TOKEN = "test-console-token"
POLICY_NAME = "sweeper_policy_name_x7"
POLICY = f'''
import numpy as np
from xpolicylab.model import Model as Base, PolicyMetadata


class Model(Base):
    """Turns the left arm's base joint steadily (0.5 rad/s), so that an e-stop has somewhere to return from."""

    @property
    def metadata(self):
        return PolicyMetadata(name="{POLICY_NAME}", cameras=("head",), chunk_size=10, image_width=64,
                              image_height=48)

    def update_obs(self, obs):
        self.pose = np.asarray(obs["state"]["joint_pos"], np.float32)

    def get_action(self):
        chunk = np.repeat(self.pose[None], 10, axis=0)
        chunk[:, 0] += 0.02 * np.arange(1, 11)
        return chunk
'''


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


RATERS = ("rater_1", "rater_2", "rater_3")
_RATER_TOKENS: dict[str, str] = {}


@pytest.fixture(scope="module")
def console(tmp_path_factory) -> Iterator[tuple[str, object]]:
    tmp = tmp_path_factory.mktemp("console")
    raters = RaterRegistry(tmp / "raters.json")
    _RATER_TOKENS.update({name: raters.add(name) for name in RATERS})
    (tmp / "sweeper.py").write_text(POLICY)
    cfg = console_config([f"packs=[{PACK}]", "suite=console_probe", f"policy={tmp / 'sweeper.py'}",
                          f"out={tmp / 'out'}", f"plans={tmp / 'plans'}"])
    session = build_session(cfg)
    session.serve_estop(TOKEN, COOKIE, "127.0.0.1", 0)
    port = _free_port()
    server = uvicorn.Server(uvicorn.Config(create_app(session, TOKEN, raters), host="127.0.0.1", port=port,
                                           log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started and time.monotonic() < deadline:
        time.sleep(0.05)
    try:
        yield f"127.0.0.1:{port}", session
    finally:
        server.should_exit = True
        thread.join(timeout=30)
        session.close()


def test_without_the_token_every_page_and_the_socket_answer_401(console) -> None:
    host, session = console
    code = session.trials[0].code
    for path in ("/", f"/rate/{code}", "/api/trials", "/api/state", f"/video/{code}.mp4", "/camera/head.jpg",
                 f"/layout/{code}/head.png", f"/api/trials/{code}/rubric"):
        assert httpx.get(f"http://{host}{path}").status_code == 401, path
        assert httpx.get(f"http://{host}{path}", headers={"Authorization": "Bearer wrong"}).status_code == 401
    for path in (f"/api/trials/{code}/reset", f"/api/trials/{code}/start", "/api/estop", "/api/stop",
                 f"/api/trials/{code}/ratings", f"/api/trials/{code}/appeals"):
        assert httpx.post(f"http://{host}{path}", json={}).status_code == 401, path
    assert httpx.post(f"http://{host}/login", data={"token": "wrong"}).status_code == 401
    for url in (f"ws://{host}/ws/state", f"ws://{host}/ws/state?token=wrong"):
        with pytest.raises(InvalidStatus) as refused:
            connect(url, open_timeout=10).close()
        assert refused.value.response.status_code == 401
    with connect(f"ws://{host}/ws/state?token={TOKEN}", open_timeout=10) as ws:
        assert "safety" in ws.recv(timeout=10)


def test_a_raters_token_opens_only_the_rater_pages_and_the_operators_does_not_score(console) -> None:
    host, session = console
    code = session.trials[0].code
    rater = {"Authorization": f"Bearer {_RATER_TOKENS['rater_1']}"}
    operator = {"Authorization": f"Bearer {TOKEN}"}
    for path in ("/", "/api/trials", "/api/state", "/camera/head.jpg", f"/layout/{code}/head.png",
                 f"/api/trials/{code}/alignment"):
        assert httpx.get(f"http://{host}{path}", headers=rater).status_code == 403, path
    for path in (f"/api/trials/{code}/reset", f"/api/trials/{code}/start", f"/api/trials/{code}/layout",
                 "/api/estop", "/api/stop", f"/api/trials/{code}/appeals"):
        assert httpx.post(f"http://{host}{path}", json={}, headers=rater).status_code == 403, path
    with pytest.raises(InvalidStatus) as refused:
        connect(f"ws://{host}/ws/state?token={_RATER_TOKENS['rater_1']}", open_timeout=10).close()
    assert refused.value.response.status_code == 403
    listed = httpx.get(f"http://{host}/api/rater/trials", headers=rater)
    assert listed.status_code == 200 and listed.json()["rater"] == "rater_1"
    assert httpx.get(f"http://{host}/rate/{code}", headers=rater).status_code == 200
    assert httpx.get(f"http://{host}/api/trials/{code}/rubric", headers=rater).json()["rater"] == "rater_1"
    answer = httpx.post(f"http://{host}/api/trials/{code}/ratings", json={"success": True}, headers=operator)
    assert answer.status_code == 403 and "does not score" in answer.json()["detail"]
    login = httpx.post(f"http://{host}/login", data={"token": _RATER_TOKENS["rater_2"]})
    assert login.status_code == 303 and login.headers["location"] == "/rate"
    assert httpx.post(f"http://{host}/login", data={"token": TOKEN}).headers["location"] == "/"


def test_an_operator_runs_and_e_stops_a_trial_and_raters_score_it_blind(console, figures) -> None:
    host, session = console
    shots = results_root() / "figures" / "console"
    shots.mkdir(parents=True, exist_ok=True)
    trial = session.trials[0]
    home = session.backend  # connected on the first reset
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=["--no-sandbox"])
        page = browser.new_page(viewport={"width": 1400, "height": 1000})
        assert page.goto(f"http://{host}/").status == 401
        page.fill("#token", TOKEN)
        page.click("#login")
        page.wait_for_selector(f"#trial-{trial.code}")
        page.screenshot(path=shots / "1_logged_in.png")

        page.click("#reset")
        page.wait_for_function("document.getElementById('safety').textContent === 'running'", timeout=60000)
        page.wait_for_selector(f"#trial-{trial.code} >> text=ready", timeout=60000)
        page.click("#layout")
        page.wait_for_function("document.getElementById('alignment').textContent.includes('head 100')",
                               timeout=30000)
        page.screenshot(path=shots / "2_scene_reset_layout_recorded.png")
        estop_url = f"http://127.0.0.1:{session.estop_process.port}/estop"  # started when the robot connected
        for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": f"Bearer {_RATER_TOKENS['rater_1']}"}):
            assert httpx.post(estop_url, headers=headers).status_code == 401
        assert home.safety.state == "running"

        page.click("#start")
        page.wait_for_function("Number(document.getElementById('step').textContent) >= 12", timeout=60000)
        driver = home._driver
        moved = float(np.abs(driver.read().joint_pos - driver.home_pose[0]).max())
        pressed = time.monotonic()
        page.keyboard.press("Escape")
        deadline = time.monotonic() + 10
        while home.safety.estop_time is None and time.monotonic() < deadline:
            time.sleep(0.001)
        assert home.safety.remote_halt.value == 1, "the press did not reach the e-stop's own process"
        figures.add("console.escape_key_to_console_told_ms(Playwright key press -> e-stop process -> safety.estop)",
                    round((home.safety.estop_time - pressed) * 1000, 1))
        page.wait_for_function("document.getElementById('safety').textContent === 'stopped'", timeout=30000)
        returned = float(np.abs(driver.read().joint_pos - driver.home_pose[0]).max())
        page.wait_for_selector(f"#trial-{trial.code} a.video", timeout=60000)
        page.screenshot(path=shots / "3_estopped_returned_to_reset.png")
        assert moved > 0.1, "the policy did not move the arm before the e-stop"
        assert returned < 0.01  # the emulator's own joint state, at the reset pose
        # A command on its way before the run saw the e-stop is refused and counted, never sent (a loaded CI
        # machine made one).
        assert trial.end_reason == "estop" and trial.counters["refused_estop"] <= 1

        video = page.request.get(f"http://{host}/video/{trial.code}.mp4")
        assert video.status == 200 and video.headers["content-type"] == "video/mp4" and len(video.body()) > 1000
        for item in (page.content(), page.request.get(f"http://{host}/api/trials").text(),
                     page.request.get(f"http://{host}/api/state").text()):
            assert POLICY_NAME not in item and session.run_id not in item

        for rater_id, touched, success, expected in (("rater_1", True, False, "recorded (1 of 3 ratings)"),
                                                     ("rater_2", True, False, "recorded (2 of 3 ratings)"),
                                                     ("rater_3", False, True, "flagged for adjudication")):
            rater = browser.new_context().new_page()  # each rater in their own browser, with their own token
            assert rater.goto(f"http://{host}/rate/{trial.code}").status == 401
            rater.fill("#token", _RATER_TOKENS[rater_id])
            rater.click("#login")
            rater.wait_for_selector(f"#trial-{trial.code} a.rate")
            assert rater.goto(f"http://{host}/").status == 403
            rater.goto(f"http://{host}/rate")
            rater.click(f"#trial-{trial.code} a.rate")
            rater.wait_for_selector(".stage[name=lifted]")
            rater.wait_for_function(f"document.getElementById('rater').textContent === {rater_id!r}")
            assert POLICY_NAME not in rater.content() and session.run_id not in rater.content()
            if touched:
                rater.check(".stage[name=touched]")
            if success:
                rater.check("#success")
            rater.click("#submit")
            rater.wait_for_function(f"document.getElementById('verdict').textContent.startsWith({expected!r})")
        rater.screenshot(path=shots / "4_rater_flagged.png")
        rater.goto(f"http://{host}/rate")
        rater.wait_for_selector(f"#trial-{trial.code} >> text=done")
        rater.screenshot(path=shots / "5_rater_list.png")
        assert page.request.post(f"http://{host}/api/trials/{trial.code}/ratings",
                                 data={"success": True}).status == 403  # the operator does not score
        appeal = page.request.post(f"http://{host}/api/trials/{trial.code}/appeals",
                                    data={"reason": "the block was misplaced at the start",
                                          "outcome": "upheld: re-run the trial"})
        assert appeal.status == 200 and appeal.json()["appeals"][0]["outcome"] == "upheld: re-run the trial"
        browser.close()

    with ResultsStore(session.store_path, readonly=True) as store:
        (row,) = store.rows(session.run_id)
    assert row.failure_reason == "estop" and row.policy_name == POLICY_NAME  # revealed in the store, not the pages
    from dojo.realeval.ratings import RatingStore

    ratings = RatingStore(session.store_path)
    marks = ratings.ratings(session.run_id, row.key)
    ratings.close()
    assert [(r.rater, r.score) for r in marks] == [("rater_1", 100 / 3), ("rater_2", 100 / 3), ("rater_3", 0.0)]
