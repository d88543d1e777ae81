"""The web console's routes (Starlette): pages, live data, takes, and the take controls.

Starting and stopping a take go through `Daemon.handle`, the function that answers the control
socket, with a control-protocol request made from the form: the same validation, the same
`busy` rules and the same errors, so the console can do nothing the socket would refuse.
Live data comes from `live.LivePublisher` slots (bounded rate, latest value only); the stream
to a browser is server-sent events, one JSON document per publisher version.

Request bodies are read as strictly as the control socket reads requests: at most
MAX_BODY_BYTES (refused with 413 before more is read, with or without a Content-Length), and
parsed by the control socket's own `parse_json_object` (no repeated keys, no lone surrogates,
no over-long integers, bounded nesting), so hostile input is a 4xx naming the field.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import logging
import threading
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError
from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.middleware import Middleware
from starlette.requests import Request
from starlette.responses import HTMLResponse, JSONResponse, Response, StreamingResponse
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from rigd.app.console.live import EVENT_WINDOWS_MS, LivePublisher
from rigd.app.console.security import ConsoleSecurity, SecurityMiddleware
from rigd.app.console.takes import TakeList, read_text_nofollow, write_text_nofollow
from rigd.app.service.protocol import MAX_MESSAGE_BYTES, PROTOCOL_VERSION, CaptureArgs, StopArgs
from rigd.app.service.requests import RequestError, parse_json_object
from rigd.core.errors import RigdError

log = logging.getLogger(__name__)

STATIC = resources.files("rigd.app.console") / "static"
#: Notes kept with a take (a text file next to it: `<take>.notes.txt`).
NOTES_SUFFIX = ".notes.txt"
_NO_STORE = {"Cache-Control": "no-store"}
#: Largest request body read (the control socket's message limit): the biggest legitimate body,
#: a start with 4000 characters of notes, is well under it.
MAX_BODY_BYTES = MAX_MESSAGE_BYTES
#: Largest notes file read back for the take list (what the console writes is at most 16 kB).
MAX_NOTES_BYTES = 64 * 1024


class StartBody(BaseModel):
    """Start a take from the console: the control protocol's capture arguments plus notes
    (strict like the control socket: "5" is not a duration)."""

    model_config = ConfigDict(extra="forbid", strict=True)

    duration_s: float | None = Field(None, description="Seconds; None: until stopped.")
    label: str | None = Field(None, description="Take name part (letters, digits, _ . -).")
    notes: str | None = Field(None, max_length=4000, description="Kept next to the take as text.")


class StopBody(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    reason: str = Field("stopped from the console", max_length=200)


class WindowBody(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    window_ms: int


@dataclass
class ConsoleContext:
    """What the routes work with: the daemon, its live publisher, the take list, the security."""

    daemon: Any
    live: LivePublisher
    takes: TakeList
    security: ConsoleSecurity
    guided: Any = None
    closing: threading.Event = field(default_factory=threading.Event)
    _ids: Iterator[int] = field(default_factory=itertools.count)

    def next_id(self) -> str:
        """Request ids for the control protocol (itertools.count: safe across worker threads)."""
        return f"console-{next(self._ids)}"


def _error(status: int, code: str, message: str, fld: str | None = None) -> JSONResponse:
    return JSONResponse({"ok": False, "error": {"code": code, "message": message, "field": fld}}, status)


class BodyTooLargeError(Exception):
    """A request body went over MAX_BODY_BYTES while it was being read."""


def _too_large() -> JSONResponse:
    return _error(413, "too_large", f"request body over {MAX_BODY_BYTES} bytes")


class BodyLimitMiddleware:
    """Refuse request bodies over `limit` bytes with 413: at once when Content-Length says so,
    else (chunked) as soon as the bytes received pass it; nothing beyond `limit` is buffered."""

    def __init__(self, app: ASGIApp, limit: int = MAX_BODY_BYTES) -> None:
        self.app = app
        self.limit = limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        for key, value in scope["headers"]:
            if key == b"content-length" and (not value.isdigit() or int(value) > self.limit):
                await _too_large()(scope, receive, send)
                return
        received = 0
        started = False

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.limit:
                    raise BodyTooLargeError()
            return message

        async def tracked_send(message: Message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, limited_receive, tracked_send)
        except BodyTooLargeError:
            if started:
                raise
            await _too_large()(scope, receive, send)


async def read_body(request: Request, model: type[BaseModel]) -> BaseModel | JSONResponse:
    """The request body as `model`, or the error response: 413 over MAX_BODY_BYTES, 400 for
    what the control socket's parser refuses (bad JSON, a repeated key, a lone surrogate, an
    over-long integer, deep nesting) and for unknown fields or wrong types, naming the field."""
    try:
        raw = await request.body()
    except BodyTooLargeError:
        return _too_large()
    try:
        data = parse_json_object(raw or b"{}", what="body", max_bytes=MAX_BODY_BYTES)
        return model.model_validate(data)
    except RequestError as exc:
        return _error(400, exc.info.code, exc.info.message, exc.info.field)
    except ValidationError as exc:
        err = exc.errors()[0]
        return _error(400, "bad_request", str(err["msg"]), ".".join(str(p) for p in err["loc"]) or None)


_STATUS_BY_CODE = {"busy": 409, "not_capturing": 409, "device_error": 503, "internal": 500}


def control_call(ctx: ConsoleContext, cmd: str, args: dict[str, Any]) -> JSONResponse:
    """Send one control-protocol request through the daemon's own request handler."""
    req = {"v": PROTOCOL_VERSION, "id": ctx.next_id(), "cmd": cmd, "args": args}
    raw = ctx.daemon.handle([json.dumps(req).encode()])
    reply = json.loads(raw)
    if reply.get("ok"):
        return JSONResponse(reply)
    code = reply["error"]["code"]
    return JSONResponse(reply, _STATUS_BY_CODE.get(code, 400))


def _page(ctx: ConsoleContext, name: str) -> str:
    """A page as stored: it holds no secret (the script reads it from the tab's sessionStorage)."""
    return (STATIC / name).read_text(encoding="utf-8")


def build_app(ctx: ConsoleContext) -> Starlette:
    """The Starlette application of the console: the live view's routes, the takes', the guided
    calibration's when it runs, and the static files."""
    routes: list[Route | Mount] = [*_live_routes(ctx), *_take_routes(ctx)]
    if ctx.guided is not None:
        routes += ctx.guided.routes()
    routes.append(Mount("/static", StaticFiles(directory=str(STATIC)), name="static"))
    middleware = [Middleware(SecurityMiddleware, security=ctx.security), Middleware(BodyLimitMiddleware)]
    return Starlette(routes=routes, middleware=middleware)


def _live_routes(ctx: ConsoleContext) -> list[Route]:
    """The pages, the daemon's status (polled and streamed), live previews, the event window."""

    async def page(request: Request) -> Response:
        # The login (`?token=` kept by the tab, never a cookie) is the security middleware's.
        name = "calibrate.html" if request.url.path.startswith("/calibrate") else "dashboard.html"
        return HTMLResponse(_page(ctx, name), headers=_NO_STORE)

    async def status(request: Request) -> Response:
        doc = await run_in_threadpool(ctx.live.fresh_status)
        return JSONResponse(doc, headers=_NO_STORE)

    async def live(request: Request) -> Response:
        async def stream() -> AsyncIterator[bytes]:
            seen = seen_guided = -1
            yield b"retry: 1000\n\n"
            while not ctx.closing.is_set():
                ctx.live.want()
                version, doc = ctx.live.state.status.get()
                if doc is not None and version != seen:
                    seen = version
                    yield f"event: status\ndata: {json.dumps(doc)}\n\n".encode()
                guided = ctx.guided.status_doc() if ctx.guided is not None else None
                if guided is not None and guided["version"] != seen_guided:
                    seen_guided = guided["version"]
                    yield f"event: guided\ndata: {json.dumps(guided)}\n\n".encode()
                await asyncio.sleep(ctx.live.interval_s)

        return StreamingResponse(stream(), media_type="text/event-stream", headers=_NO_STORE)

    async def preview(request: Request) -> Response:
        device = request.path_params["device"]
        ctx.live.want()
        with ctx.live.state.lock:
            slot = ctx.live.state.previews.get(device)
        value = None if slot is None else slot.get()[1]
        if value is None:
            return _error(404, "not_found", f"no preview of {device!r} yet (previews come while a take runs)")
        return Response(value.jpeg, media_type="image/jpeg", headers=_NO_STORE)

    async def set_window(request: Request) -> Response:
        body = await read_body(request, WindowBody)
        if isinstance(body, JSONResponse):
            return body
        assert isinstance(body, WindowBody)
        if body.window_ms not in EVENT_WINDOWS_MS:
            allowed = list(EVENT_WINDOWS_MS)
            return _error(400, "bad_request", f"window_ms must be one of {allowed}", "window_ms")
        ctx.live.event_window_ms = body.window_ms
        return JSONResponse({"ok": True, "window_ms": body.window_ms})

    return [
        Route("/", page),
        Route("/calibrate", page),
        Route("/api/status", status),
        Route("/api/live", live),
        Route("/api/preview/{device}.jpg", preview),
        Route("/api/event-window", set_window, methods=["POST"]),
    ]


def _take_routes(ctx: ConsoleContext) -> list[Route]:
    """Starting and stopping a take, and the takes on disk (list, notes, previews, event rates)."""

    async def start_take(request: Request) -> Response:
        body = await read_body(request, StartBody)
        if isinstance(body, JSONResponse):
            return body
        assert isinstance(body, StartBody)
        args = body.model_dump(include=set(CaptureArgs.model_fields), exclude_none=True)
        resp = await run_in_threadpool(control_call, ctx, "capture", args)
        if resp.status_code == 200 and body.notes:
            reply = json.loads(bytes(resp.body))
            path = Path(reply["result"]["take"])
            try:
                await run_in_threadpool(_write_notes, path, body.notes)
            except OSError as exc:  # the take runs; the page says the notes were not kept
                log.warning("console: notes of %s not written: %s", path.name, exc)
                reply["notes_error"] = f"notes not written: {exc.strerror or exc}"
                return JSONResponse(reply)
        return resp

    async def stop_take(request: Request) -> Response:
        body = await read_body(request, StopBody)
        if isinstance(body, JSONResponse):
            return body
        assert isinstance(body, StopBody)
        args = body.model_dump(include=set(StopArgs.model_fields))
        return await run_in_threadpool(control_call, ctx, "stop", args)

    async def takes(request: Request) -> Response:
        running = (await run_in_threadpool(ctx.live.fresh_status)).get("take")

        def listing() -> list[dict[str, Any]]:
            out = []
            for e in ctx.takes.entries(running):
                doc = e.model_dump(mode="json")
                doc["notes"] = _read_notes(Path(e.path))
                out.append(doc)
            return out

        try:
            return JSONResponse({"takes": await run_in_threadpool(listing)}, headers=_NO_STORE)
        except RigdError as exc:
            return _error(500, "take_error", str(exc))

    async def take_preview(request: Request) -> Response:
        try:
            jpeg = await run_in_threadpool(
                ctx.takes.preview, request.path_params["name"], request.path_params["camera"]
            )
        except RigdError as exc:
            return _error(404, "not_found", str(exc))
        return Response(jpeg, media_type="image/jpeg", headers={"Cache-Control": "max-age=60"})

    async def take_rates(request: Request) -> Response:
        try:
            rates = await run_in_threadpool(ctx.takes.event_rates, request.path_params["name"])
        except RigdError as exc:
            return _error(404, "not_found", str(exc))
        return JSONResponse(rates)

    return [
        Route("/api/takes", takes),
        Route("/api/takes/start", start_take, methods=["POST"]),
        Route("/api/takes/stop", stop_take, methods=["POST"]),
        Route("/api/takes/{name}/preview/{camera}.jpg", take_preview),
        Route("/api/takes/{name}/rates", take_rates),
    ]


def _notes_path(take: Path) -> Path:
    return take.with_name(take.name + NOTES_SUFFIX)


def _write_notes(take: Path, notes: str) -> None:
    """Never through a symlink planted where the notes go (OSError, answered as an error)."""
    write_text_nofollow(_notes_path(take), notes)


def _read_notes(take: Path) -> str | None:
    """None when there are none; a symlink or something unreadable is said so in the listing."""
    try:
        return read_text_nofollow(_notes_path(take), MAX_NOTES_BYTES)
    except OSError as exc:
        log.info("console: notes of %s not read: %s", take.name, exc)  # the listing says so
        return f"(notes not read: {exc.strerror or exc})"
