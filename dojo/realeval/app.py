"""The operator console and the raters' pages: a small FastAPI app over one `ConsoleSession`.

Two kinds of credential reach it. The operator's bearer token (one per console) opens everything but scoring;
each rater's own token (`dojo.realeval.raters`, issued by `dojo console add-rater NAME`) opens only the rater
pages (`RATER_PATHS`: the list of trials to rate, a trial's rubric and video, and posting one's own rating,
which is recorded under the rater's name). A credential is an `Authorization: Bearer` header, the cookie
`/login` sets, or (for the socket, which browsers cannot give headers) `?token=`. Without a valid one every
request answers 401 (a page's 401 carries the login form), so a policy's submitter, who talks to the policy
server and never to this one, cannot reach it; a rater's token anywhere else answers 403, and the operator's
token does not score (403). Nothing served names the policy or the run: trials are known by their blind codes.
"""

from __future__ import annotations

import asyncio
import io
import re
import secrets
from collections.abc import Awaitable, Callable, MutableMapping
from http.cookies import SimpleCookie
from typing import Any
from urllib.parse import parse_qs

from fastapi import Body, FastAPI, Form, HTTPException, Request
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, RedirectResponse, Response
from starlette.websockets import WebSocket, WebSocketDisconnect

from dojo.realeval.pages import CONSOLE_PAGE, FORBIDDEN_PAGE, LOGIN_PAGE, RATER_PAGE, RATERS_PAGE
from dojo.realeval.raters import RaterRegistry
from dojo.realeval.ratings import Rating, RatingStore, judge, rubric_score
from dojo.realeval.session import ConsoleSession

COOKIE = "dojo_console"
STATE_PERIOD_S = 0.1
"""How often the live-state socket sends the robot's state."""

OPERATOR = "operator"
PRINCIPAL = "dojo.principal"
"""Scope key the guard sets: (OPERATOR, None) or ("rater", the rater's name)."""
RATER_PATHS = re.compile(r"^/(rate(/[^/]+)?|api/rater/trials|api/trials/[^/]+/(rubric|ratings)|video/[^/]+\.mp4)$")
"""What a rater's token opens: nothing of the robot, the queue's state, the layouts or the appeals."""

Scope = MutableMapping[str, Any]
ASGIApp = Callable[[Scope, Callable[[], Awaitable[Any]], Callable[[Any], Awaitable[None]]], Awaitable[None]]


class Credentials:
    """The operator's `token` and the raters' tokens in `raters`: whose a given token is."""

    def __init__(self, token: str, raters: RaterRegistry | None) -> None:
        self.token, self.raters = token, raters

    def principal(self, given: list[str]) -> tuple[str, str | None] | None:
        """Who the first valid token of `given` belongs to: (OPERATOR, None), ("rater", name), or None."""
        for candidate in given:
            if not candidate:
                continue
            if secrets.compare_digest(candidate, self.token):
                return OPERATOR, None
            name = self.raters.identify(candidate) if self.raters is not None else None
            if name is not None:
                return "rater", name
        return None


class TokenGuard:
    """ASGI middleware: only requests with a valid credential reach the app, a rater's only on `RATER_PATHS`
    (see the module docstring)."""

    def __init__(self, app: ASGIApp, credentials: Credentials) -> None:
        self.app, self.credentials = app, credentials

    async def __call__(self, scope: Scope, receive: Any, send: Any) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        if scope["type"] == "http" and scope["path"] == "/login" and scope["method"] == "POST":
            await self.app(scope, receive, send)  # checks the token itself
            return
        principal = self.credentials.principal(_given_tokens(scope))
        if principal is not None and (principal[0] == OPERATOR or RATER_PATHS.match(scope["path"])):
            scope[PRINCIPAL] = principal
            await self.app(scope, receive, send)
            return
        status, message = (401, "the console's token is needed") if principal is None else \
            (403, "a rater's token opens only the rater pages (/rate)")
        if scope["type"] == "websocket":  # refuse the handshake with an HTTP status (WebSocket denial response)
            await send({"type": "websocket.http.response.start", "status": status,
                        "headers": [(b"content-type", b"text/plain")]})
            await send({"type": "websocket.http.response.body", "body": f"{status}: {message}".encode()})
            return
        if scope["method"] == "GET":
            response: Response = HTMLResponse(LOGIN_PAGE if status == 401 else FORBIDDEN_PAGE, status_code=status)
        else:
            response = JSONResponse({"detail": message}, status_code=status)
        await response(scope, receive, send)


def _given_tokens(scope: Scope) -> list[str]:
    """The tokens a request carries: bearer header, login cookie, `?token=`."""
    headers = {k.decode().lower(): v.decode() for k, v in scope.get("headers", [])}
    given = [headers.get("authorization", "").removeprefix("Bearer ").strip()]
    cookie = SimpleCookie(headers.get("cookie", ""))
    if COOKIE in cookie:
        given.append(cookie[COOKIE].value)
    return given + parse_qs(scope.get("query_string", b"").decode()).get("token", [])


def create_app(session: ConsoleSession, token: str, raters: RaterRegistry | None = None) -> Any:
    """The console app for `session`, guarded by the operator's `token` and the raters' tokens in `raters`."""
    credentials = Credentials(token, raters)
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

    def key(trial: Any) -> tuple[str, int, int]:
        return trial.item.plan_hash, trial.item.eval_seed, trial.item.episode

    @app.post("/login")
    def login(token_given: str = Form(alias="token")) -> Response:
        """The operator lands on the console, a rater on the list of trials to rate."""
        principal = credentials.principal([token_given])
        if principal is None:
            return HTMLResponse(LOGIN_PAGE, status_code=401)
        response = RedirectResponse("/" if principal[0] == OPERATOR else "/rate", status_code=303)
        response.set_cookie(COOKIE, token_given, httponly=True, samesite="strict")
        return response

    @app.get("/", response_class=HTMLResponse)
    def console() -> str:
        return CONSOLE_PAGE

    @app.get("/rate", response_class=HTMLResponse)
    def rater_list() -> str:
        return RATERS_PAGE

    @app.get("/api/rater/trials")
    def rater_trials(request: Request) -> dict[str, Any]:
        """The trials that have run, by blind code and task, and whether this rater has scored each."""
        rater_id = request.scope[PRINCIPAL][1]
        done = [t for t in session.trials if t.status == "done"]
        store = RatingStore(session.store_path)
        try:
            rated = [any(r.rater == rater_id for r in store.ratings(session.run_id, key(t))) for t in done]
        finally:
            store.close()
        return {"rater": rater_id, "trials": [{"code": t.code, "task": t.item.task, "rated": r}
                                              for t, r in zip(done, rated)]}

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
    def rubric(code: str, request: Request) -> dict[str, Any]:
        trial = trial_or_404(code)
        plan = session.plan(trial.item)
        stages = [{"name": s["name"], "weight": s.get("weight", 1.0)} for s in plan.program.get("stages", [])]
        return {"code": code, "task": trial.item.task, "instruction": plan.instruction, "stages": stages,
                "status": trial.status, "rater": request.scope[PRINCIPAL][1]}

    @app.post("/api/trials/{code}/ratings")
    def rate(code: str, request: Request, body: dict[str, Any] = Body(...)) -> dict[str, Any]:
        """A rating, recorded under the name the rater's token was issued to."""
        role, rater_id = request.scope[PRINCIPAL]
        if role == OPERATOR:
            raise HTTPException(403, "the operator's token does not score: raters score with their own token "
                                     "(dojo console add-rater NAME)")
        trial = trial_or_404(code)
        if trial.status != "done":
            raise HTTPException(409, f"trial {code} has not run yet")
        stages = {str(k): bool(v) for k, v in dict(body.get("stages", {})).items()}
        score = rubric_score(session.plan(trial.item).program.get("stages", []), stages)
        store = RatingStore(session.store_path)
        try:
            store.rate(session.run_id, key(trial), Rating(rater_id, bool(body.get("success")), stages, score))
            verdict = judge(store.ratings(session.run_id, key(trial)))
        finally:
            store.close()
        return {"ratings": len(verdict.ratings), "settled": verdict.settled, "flagged": verdict.flagged,
                "success": verdict.success, "score": verdict.score, "reason": verdict.reason}

    @app.post("/api/trials/{code}/appeals")
    def appeal(code: str, body: dict[str, Any] = Body(...)) -> dict[str, Any]:
        """An appeal against a trial's result, recorded by the operator (its reason, and later its outcome)."""
        trial = trial_or_404(code)
        store = RatingStore(session.store_path)
        try:
            appeal_id = act(lambda: store.appeal(session.run_id, key(trial), str(body.get("reason", ""))))
            if body.get("outcome"):
                store.decide(appeal_id, str(body["outcome"]))
            return {"id": appeal_id, "appeals": store.appeals(session.run_id, key(trial))}
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

    return TokenGuard(app, credentials)


def _jpeg(image: Any) -> bytes:
    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(image).save(out, format="JPEG", quality=85)
    return out.getvalue()
