"""The operator console and the raters' pages: a small FastAPI app over one `ConsoleSession`.

Every page, API call, image, video and the live-state WebSocket needs the session's bearer token: an
`Authorization: Bearer` header, the cookie `/login` sets, or (for the socket, which browsers cannot give
headers) `?token=`. Without it every request answers 401 (a page's 401 carries the login form), so a
policy's submitter, who talks to the policy server and never to this one, cannot reach it. Nothing served names
the policy or the run: trials are known by their blind codes.
"""

from __future__ import annotations

import asyncio
import io
import secrets
from collections.abc import Awaitable, Callable, MutableMapping
from http.cookies import SimpleCookie
from typing import Any
from urllib.parse import parse_qs

from fastapi import Body, FastAPI, Form, HTTPException
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, RedirectResponse, Response
from starlette.websockets import WebSocket, WebSocketDisconnect

from dojo.realeval.pages import CONSOLE_PAGE, LOGIN_PAGE, RATER_PAGE
from dojo.realeval.ratings import Rating, RatingStore, judge, rubric_score
from dojo.realeval.session import ConsoleSession

COOKIE = "dojo_console"
STATE_PERIOD_S = 0.1
"""How often the live-state socket sends the robot's state."""

Scope = MutableMapping[str, Any]
ASGIApp = Callable[[Scope, Callable[[], Awaitable[Any]], Callable[[Any], Awaitable[None]]], Awaitable[None]]


class TokenGuard:
    """ASGI middleware: only requests that carry `token` reach the app (see the module docstring)."""

    def __init__(self, app: ASGIApp, token: str) -> None:
        self.app, self.token = app, token

    async def __call__(self, scope: Scope, receive: Any, send: Any) -> None:
        if scope["type"] not in ("http", "websocket") or self._allowed(scope):
            await self.app(scope, receive, send)
            return
        if scope["type"] == "websocket":  # refuse the handshake with an HTTP 401 (WebSocket denial response)
            await send({"type": "websocket.http.response.start", "status": 401,
                        "headers": [(b"content-type", b"text/plain")]})
            await send({"type": "websocket.http.response.body", "body": b"401: the console's token is needed"})
            return
        response = HTMLResponse(LOGIN_PAGE, status_code=401) if scope["method"] == "GET" \
            else JSONResponse({"detail": "the console's token is needed"}, status_code=401)
        await response(scope, receive, send)

    def _allowed(self, scope: Scope) -> bool:
        if scope["type"] == "http" and scope["path"] == "/login" and scope["method"] == "POST":
            return True  # checks the token itself
        headers = {k.decode().lower(): v.decode() for k, v in scope.get("headers", [])}
        given = [headers.get("authorization", "").removeprefix("Bearer ").strip()]
        cookie = SimpleCookie(headers.get("cookie", ""))
        if COOKIE in cookie:
            given.append(cookie[COOKIE].value)
        given += parse_qs(scope.get("query_string", b"").decode()).get("token", [])
        return any(g and secrets.compare_digest(g, self.token) for g in given)


def create_app(session: ConsoleSession, token: str) -> Any:
    """The console app for `session`, guarded by `token`."""
    app = FastAPI(title="RoboDojo RealEval console", docs_url=None, redoc_url=None, openapi_url=None)

    def trial_or_404(code: str) -> Any:
        try:
            return session.trial(code)
        except KeyError as exc:
            raise HTTPException(404, str(exc)) from exc

    def act(action: Callable[[], Any]) -> Any:
        try:
            return action()
        except (RuntimeError, KeyError) as exc:
            raise HTTPException(409, str(exc)) from exc

    @app.post("/login")
    def login(token_given: str = Form(alias="token")) -> Response:
        if not secrets.compare_digest(token_given, token):
            return HTMLResponse(LOGIN_PAGE, status_code=401)
        response = RedirectResponse("/", status_code=303)
        response.set_cookie(COOKIE, token, httponly=True, samesite="strict")
        return response

    @app.get("/", response_class=HTMLResponse)
    def console() -> str:
        return CONSOLE_PAGE

    @app.get("/rate/{code}", response_class=HTMLResponse)
    def rater(code: str) -> str:
        trial_or_404(code)
        return RATER_PAGE

    @app.get("/api/trials")
    def trials() -> list[dict[str, Any]]:
        return [t.public() for t in session.trials]

    @app.get("/api/state")
    def state() -> dict[str, Any]:
        return session.state()

    @app.post("/api/trials/{code}/reset")
    def reset(code: str) -> dict[str, str]:
        act(lambda: session.reset(code))
        return {"queued": "reset"}

    @app.post("/api/trials/{code}/start")
    def start(code: str) -> dict[str, str]:
        act(lambda: session.start(code))
        return {"queued": "start"}

    @app.post("/api/stop")
    def stop() -> dict[str, str]:
        session.stop()
        return {"stopped": "at the next step"}

    @app.post("/api/estop")
    async def estop() -> dict[str, float]:
        """On the event loop itself, not the thread pool the other calls wait for: the hold is sent at once."""
        return {"estop_at": session.estop()}

    @app.post("/api/trials/{code}/layout")
    def record_layout(code: str) -> dict[str, str]:
        folder = act(lambda: session.record_layout(code))
        return {"recorded": folder.name}

    @app.get("/api/trials/{code}/alignment")
    def alignment(code: str) -> dict[str, float]:
        trial_or_404(code)
        return session.alignment(code)

    @app.get("/camera/{camera}.jpg")
    def camera(camera: str) -> Response:
        if camera not in session.live:
            raise HTTPException(404, f"no live frame of camera {camera!r} yet")
        return Response(_jpeg(session.live[camera]), media_type="image/jpeg", headers={"Cache-Control": "no-store"})

    @app.get("/layout/{code}/{camera}.png")
    def reference(code: str, camera: str) -> Response:
        trial_or_404(code)
        path = session.reference(code, camera)
        if path is None:
            raise HTTPException(404, f"trial {code} has no reference layout for camera {camera!r}")
        return FileResponse(path, media_type="image/png")

    @app.get("/video/{code}.mp4")
    def video(code: str) -> Response:
        trial = trial_or_404(code)
        if trial.video is None:
            raise HTTPException(404, f"trial {code} has no video yet")
        return FileResponse(trial.video, media_type="video/mp4")

    @app.get("/api/trials/{code}/rubric")
    def rubric(code: str) -> dict[str, Any]:
        trial = trial_or_404(code)
        plan = session.plan(trial.item)
        stages = [{"name": s["name"], "weight": s.get("weight", 1.0)} for s in plan.program.get("stages", [])]
        return {"code": code, "task": trial.item.task, "instruction": plan.instruction, "stages": stages,
                "status": trial.status}

    @app.post("/api/trials/{code}/ratings")
    def rate(code: str, body: dict[str, Any] = Body(...)) -> dict[str, Any]:
        trial = trial_or_404(code)
        if trial.status != "done":
            raise HTTPException(409, f"trial {code} has not run yet")
        rater_id = str(body.get("rater", "")).strip()
        if not rater_id:
            raise HTTPException(422, "a rating needs the rater's id")
        stages = {str(k): bool(v) for k, v in dict(body.get("stages", {})).items()}
        score = rubric_score(session.plan(trial.item).program.get("stages", []), stages)
        store = RatingStore(session.store_path)
        try:
            key = (trial.item.plan_hash, trial.item.eval_seed, trial.item.episode)
            store.rate(session.run_id, key, Rating(rater_id, bool(body.get("success")), stages, score))
            verdict = judge(store.ratings(session.run_id, key))
        finally:
            store.close()
        return {"ratings": len(verdict.ratings), "settled": verdict.settled, "flagged": verdict.flagged,
                "success": verdict.success, "score": verdict.score, "reason": verdict.reason}

    @app.post("/api/trials/{code}/appeals")
    def appeal(code: str, body: dict[str, Any] = Body(...)) -> dict[str, Any]:
        trial = trial_or_404(code)
        store = RatingStore(session.store_path)
        try:
            key = (trial.item.plan_hash, trial.item.eval_seed, trial.item.episode)
            appeal_id = act(lambda: store.appeal(session.run_id, key, str(body.get("reason", ""))))
            if body.get("outcome"):
                store.decide(appeal_id, str(body["outcome"]))
            return {"id": appeal_id, "appeals": store.appeals(session.run_id, key)}
        except ValueError as exc:
            raise HTTPException(422, str(exc)) from exc
        finally:
            store.close()

    @app.websocket("/ws/state")
    async def live_state(socket: WebSocket) -> None:
        await socket.accept()
        try:
            while True:
                await socket.send_json(session.state())
                await asyncio.sleep(STATE_PERIOD_S)
        except (WebSocketDisconnect, RuntimeError):
            return

    return TokenGuard(app, token)


def _jpeg(image: Any) -> bytes:
    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(image).save(out, format="JPEG", quality=85)
    return out.getvalue()
