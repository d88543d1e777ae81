"""Guided calibration from the web console: one `GuidedRun` on a worker thread, its state in slots.

The worker offers the newest frame to the session as fast as detection allows (as the CLI does);
the browser sees, at the console's rate, the frame with the detected corners and the ghost outline
of the next pose drawn in, the coverage, the sigmas against the target and the kept views. The
technician can drop a view and finish: the calibration is written as OpenCV YAML and JSON with
an HTML report into the console's calibration directory (and, when asked, into a complete take's
`/calibration/<device>`), and the page links the files.

The guided run opens the rig's devices itself, so it holds them in the daemon (`hold_devices`):
it is refused while a take runs, and a take asked for meanwhile, from the console or the control
socket, is answered `busy` (on the sim rig it uses a world of its own).

Files are written and served only as plain files directly in the calibration directory, which
must not itself be a symlink: a link planted there is refused, never followed.
"""

from __future__ import annotations

import logging
import mimetypes
import os
import stat
import threading
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route

from calibration.boards import parse_board
from calibration.errors import CalibrationError
from calibration.guided import SIGMA_NAMES
from calibration.io import write_json
from calibration.view_planning import TILT_BINS
from rigd.app.console.app import read_body
from rigd.app.console.live import LatestSlot, LivePublisher
from rigd.app.console.takes import TakeList, check_name, file_in, plain_dir
from rigd.app.service.requests import RequestError
from rigd.app.workflows.guided import (
    DEFAULT_BOARD,
    GuidedOptions,
    GuidedRun,
    own_sim_world,
    verdict,
    views_text,
)
from rigd.core.errors import RigdError
from rigd.take.calibration import store_calibration

log = logging.getLogger(__name__)

_NO_STORE = {"Cache-Control": "no-store"}
#: Largest calibration file served (results and reports are far smaller).
MAX_FILE_BYTES = 64 * 1024 * 1024


class GuidedStartBody(BaseModel):
    """What the technician picks on /calibrate."""

    model_config = ConfigDict(extra="forbid")

    camera: str = Field(max_length=64)
    board: str = Field(DEFAULT_BOARD, max_length=64)
    target_sigma_px: float = Field(0.5, gt=0, le=50)
    min_views: int = Field(6, ge=3, le=100)
    still_px: float = Field(1.0, gt=0, le=100)
    max_seconds: float = Field(600.0, gt=0, le=3600)


class FinishBody(BaseModel):
    model_config = ConfigDict(extra="forbid")

    into_take: str | None = Field(
        None, max_length=200, description="Also store the result in this take of take_dir."
    )


class CancelBody(BaseModel):
    """Nothing: but a body is read as strictly as any other (no unknown fields)."""

    model_config = ConfigDict(extra="forbid")


class DropBody(BaseModel):
    model_config = ConfigDict(extra="forbid")

    index: int = Field(ge=0)


def _stamp() -> str:
    return datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")


def annotate(image: np.ndarray, corners: np.ndarray | None, ghost: list[list[float]] | None) -> np.ndarray:
    """BGR copy of `image` with the detected corners (green) and the next pose's outline (cyan)."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        lo, hi = float(img.min()), float(img.max())
        img = ((img - lo) * (255.0 / max(hi - lo, 1e-9))).astype(np.uint8)
    out = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else np.ascontiguousarray(img[:, :, ::-1])
    scale = max(1, round(out.shape[1] / 320))
    if ghost is not None:
        pts = np.round(np.asarray(ghost)).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(out, [pts], True, (255, 255, 0), scale, cv2.LINE_AA)
    if corners is not None:
        for x, y in np.asarray(corners).reshape(-1, 2):
            cv2.circle(out, (round(float(x)), round(float(y))), 2 * scale, (0, 255, 0), -1, cv2.LINE_AA)
    return out


class GuidedController:
    """At most one guided run at a time, for the console (see the module docstring)."""

    def __init__(self, daemon: Any, live: LivePublisher, out_dir: Path, takes: TakeList) -> None:
        self.daemon = daemon
        self.live = live
        self.out_dir = out_dir
        self.takes = takes
        self._into_take: Path | None = None
        self._lock = threading.Lock()
        self._run: GuidedRun | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._finish = threading.Event()
        self._drops: list[int] = []
        self.image: LatestSlot[bytes] = LatestSlot()
        self._doc: dict[str, Any] = {"state": "idle"}
        self._doc_version = 0
        self._last_image = 0.0

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def devices(self) -> dict[str, Any]:
        cfg = self.daemon.config
        return {
            "cameras": [c.name for c in cfg.cameras],
            "event_sensors": [s.name for s in cfg.event_sensors],
            "board": DEFAULT_BOARD,
        }

    def status_doc(self) -> dict[str, Any] | None:
        """The newest state for the live stream (None while nothing ever ran)."""
        with self._lock:
            if self._doc.get("state") == "idle" and self._doc_version == 0:
                return None
            return dict(self._doc, version=self._doc_version, image=self.image.get()[0])

    def _set_doc(self, **doc: Any) -> None:
        with self._lock:
            self._doc = doc
            self._doc_version += 1

    def start(self, body: GuidedStartBody) -> dict[str, Any]:
        if self.running:
            raise RigdError("a guided calibration is already running")
        known = self.devices()
        if body.camera not in known["cameras"] + known["event_sensors"]:
            raise RequestError("bad_request", f"no device {body.camera!r} in the rig", "camera")
        state = self.daemon.telemetry().state
        if state != "idle":
            raise RigdError(f"the rig is {state}: guided calibration needs it idle (stop the take first)")
        try:
            board = parse_board(body.board)
        except (CalibrationError, ValueError) as exc:
            raise RigdError(f"board {body.board!r}: {exc}") from exc
        stamp = _stamp()
        self.out_dir.mkdir(parents=True, exist_ok=True)
        plain_dir(self.out_dir, "calibration directory")
        options = GuidedOptions(
            camera=body.camera,
            out=self.out_dir / f"{body.camera}-{stamp}.yaml",
            report=self.out_dir / f"{body.camera}-{stamp}.html",
            board=board,
            target_sigma_px=body.target_sigma_px,
            max_seconds=body.max_seconds,
            still_px=body.still_px,
            min_views=body.min_views,
        )
        self.daemon.hold_devices(f"the guided calibration of {body.camera} (web console)")
        try:
            run = GuidedRun(options, own_sim_world(self.daemon.config))
            started = run.open()
        except BaseException:
            self.daemon.release_devices()
            raise
        self._stop.clear()
        self._finish.clear()
        self._drops = []
        self._into_take = None
        self._run = run
        self._set_doc(state="running", camera=body.camera, spec=started.spec, hint=started.first_hint)
        self._thread = threading.Thread(target=self._work, args=(run,), name="console-guided", daemon=True)
        self._thread.start()
        log.info("console: guided calibration of %s started (%s)", body.camera, started.spec)
        return {"camera": body.camera, "spec": started.spec, "frame_size": list(started.frame_size)}

    def _work(self, run: GuidedRun) -> None:
        o = run.options
        fb = None
        try:
            while not self._stop.is_set() and not self._finish.is_set() and not run.budget.spent:
                with self._lock:
                    drops, self._drops = self._drops, []
                for i in sorted(drops, reverse=True):
                    run.session.drop_view(i)
                looked = run.step(0.5)
                if looked is None:
                    continue
                fb, image = looked
                self._publish(run, fb.model_dump(mode="json"), image)
            if self._stop.is_set() and not self._finish.is_set():
                run.close()
                self._set_doc(state="cancelled", camera=o.camera)
                return
            self._set_doc(state="finishing", camera=o.camera)
            self._write(run)
        except Exception as exc:
            # The session ends; the page shows why, the log has the traceback.
            log.exception("console: guided calibration of %s failed", o.camera)
            run.close()
            self._set_doc(state="failed", camera=o.camera, error=f"{type(exc).__name__}: {exc}")
        finally:
            self.daemon.release_devices()

    def _publish(self, run: GuidedRun, fb: dict[str, Any], image: np.ndarray) -> None:
        session = run.session
        ghost = session.hint_outline()
        now = time.monotonic()
        if now - self._last_image >= self.live.interval_s:
            self._last_image = now
            det = session.last_detection
            img = annotate(image, None if det is None else det.image_points, ghost)
            width = 640
            if img.shape[1] > width:
                size = (width, round(img.shape[0] * width / img.shape[1]))
                img = np.asarray(cv2.resize(img, size, interpolation=cv2.INTER_AREA), np.uint8)
            ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 75])
            if ok:
                self.image.put(buf.tobytes())
        o = run.options
        self._set_doc(
            state="running",
            camera=o.camera,
            feedback=fb,
            views=session.view_list(),
            grid=list(session.grid),
            tilt_bins=list(TILT_BINS),
            frame_size=list(session.image_size),
            ghost=ghost,
            target_sigma_px=o.target_sigma_px,
            min_views=o.min_views,
            done_views=o.done_views,
            sigma_names=list(SIGMA_NAMES),
            seconds_left=run.budget.left(),
        )

    def _write(self, run: GuidedRun) -> None:
        o = run.options
        _refuse_links(o.out_path, o.out_path.with_suffix(".json"), o.report)
        outcome = run.finish()
        reached, text = verdict(outcome, o.target_sigma_px, o.done_views)
        files: dict[str, str] = {}
        if outcome.result is not None:
            json_path = o.out_path.with_suffix(".json")
            write_json(outcome.result, json_path)
            files = {"yaml": o.out_path.name, "json": json_path.name}
            if o.report is not None:
                files["report"] = o.report.name
            if self._into_take is not None:
                summary = outcome.result.summary()
                source = f"guided calibration from the console ({outcome.n_views} views)"
                store_calibration(self._into_take, o.camera, intrinsics=summary, source=source)
                files["take"] = self._into_take.name
            sig = {k: round(outcome.result.std_devs[k], 4) for k in SIGMA_NAMES}
        else:
            sig = {}
        log.info("console: guided calibration of %s: %s", o.camera, text)
        self._set_doc(
            state="finished",
            camera=o.camera,
            reached=reached,
            verdict=text,
            n_views=outcome.n_views,
            views_text=views_text(outcome),
            sigmas=sig,
            rms_px=None if outcome.result is None else outcome.result.rms_px,
            warnings=[] if outcome.result is None else list(outcome.result.warnings),
            files=files,
        )

    def drop(self, index: int) -> None:
        if not self.running:
            raise RigdError("no guided calibration is running")
        with self._lock:
            self._drops.append(index)

    def finish(self, into_take: str | None = None) -> None:
        """End the session and write the result (and store it in take `into_take` of take_dir)."""
        if not self.running:
            raise RigdError("no guided calibration is running")
        path = None
        if into_take is not None:
            path = self.takes.path_of(into_take)
            entry = self.takes.entry(path)
            if entry.status != "complete":
                raise RigdError(f"take {into_take} is {entry.status}; calibrations go into complete takes")
            if self.run_device() not in entry.cameras + entry.event_sensors:
                raise RigdError(f"take {into_take} has no device {self.run_device()!r}")
        self._into_take = path
        self._finish.set()

    def _read_file(self, name: str) -> bytes:
        """Calibration file `name`: a plain file of the calibration directory, opened without
        following a link swapped in since the check, at most MAX_FILE_BYTES."""
        check_name(name, "calibration file")  # the name first: a bad one is refused as such
        path = file_in(plain_dir(self.out_dir, "calibration directory"), name, "calibration file")
        with os.fdopen(os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK), "rb") as f:
            st = os.fstat(f.fileno())
            if not stat.S_ISREG(st.st_mode):
                raise RigdError(f"calibration file {name!r} is not a regular file")
            if st.st_size > MAX_FILE_BYTES:
                raise RigdError(
                    f"calibration file {name!r} has {st.st_size} bytes; served up to {MAX_FILE_BYTES}"
                )
            return f.read(MAX_FILE_BYTES)

    def run_device(self) -> str | None:
        return None if self._run is None else self._run.options.camera

    def cancel(self) -> None:
        self._stop.set()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)

    # -- routes -------------------------------------------------------------------------------
    def routes(self) -> list[Route]:
        async def info(request: Request) -> Response:
            return JSONResponse({"devices": self.devices(), "status": self.status_doc()}, headers=_NO_STORE)

        async def start(request: Request) -> Response:
            body = await read_body(request, GuidedStartBody)
            if isinstance(body, JSONResponse):
                return body
            assert isinstance(body, GuidedStartBody)
            try:
                return JSONResponse({"ok": True, "result": await run_in_threadpool(self.start, body)})
            except RequestError as exc:
                status = 400 if exc.info.code == "bad_request" else 409
                return JSONResponse({"ok": False, "error": exc.info.model_dump()}, status)
            except RigdError as exc:
                return JSONResponse({"ok": False, "error": {"code": "busy", "message": str(exc)}}, 409)

        async def drop(request: Request) -> Response:
            body = await read_body(request, DropBody)
            if isinstance(body, JSONResponse):
                return body
            assert isinstance(body, DropBody)
            try:
                self.drop(body.index)
            except RigdError as exc:
                return _bad(str(exc))
            return JSONResponse({"ok": True})

        async def finish(request: Request) -> Response:
            body = await read_body(request, FinishBody)
            if isinstance(body, JSONResponse):
                return body
            assert isinstance(body, FinishBody)
            try:
                await run_in_threadpool(self.finish, body.into_take)
            except RigdError as exc:
                return _bad(str(exc))
            return JSONResponse({"ok": True})

        async def cancel(request: Request) -> Response:
            body = await read_body(request, CancelBody)
            if isinstance(body, JSONResponse):
                return body
            self.cancel()
            return JSONResponse({"ok": True})

        async def image(request: Request) -> Response:
            self.live.want()
            jpeg = self.image.get()[1]
            if jpeg is None:
                return JSONResponse({"ok": False, "error": {"code": "not_found", "message": "no image"}}, 404)
            return Response(jpeg, media_type="image/jpeg", headers=_NO_STORE)

        async def files(request: Request) -> Response:
            name = request.path_params["name"]
            try:
                data = await run_in_threadpool(self._read_file, name)
            except (RigdError, OSError) as exc:
                return JSONResponse({"ok": False, "error": {"code": "not_found", "message": str(exc)}}, 404)
            media = mimetypes.guess_type(name)[0] or "application/octet-stream"
            return Response(data, media_type=media, headers=_NO_STORE)

        return [
            Route("/api/guided", info),
            Route("/api/guided/start", start, methods=["POST"]),
            Route("/api/guided/drop", drop, methods=["POST"]),
            Route("/api/guided/finish", finish, methods=["POST"]),
            Route("/api/guided/cancel", cancel, methods=["POST"]),
            Route("/api/guided/image.jpg", image),
            Route("/api/guided/files/{name}", files),
        ]


def _refuse_links(*paths: Path | None) -> None:
    """Refuse to write where a symlink waits (planted by someone who can write take_dir)."""
    for path in paths:
        if path is not None and path.is_symlink():
            raise RigdError(f"{path} is a symbolic link; the console does not write through links")
        if path is not None:
            plain_dir(path.parent, "calibration directory")


def _bad(message: str) -> JSONResponse:
    return JSONResponse({"ok": False, "error": {"code": "bad_request", "message": message}}, 400)
