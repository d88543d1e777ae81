"""Control requests as they arrive: ROUTER framing, the JSON body (one object, no repeated
key, within the size limit), the command and its arguments validated against the protocol's
models, and the structured error a failed request is answered with."""

from __future__ import annotations

import json
import logging
from typing import Any

from pydantic import BaseModel, ValidationError

from rigd.app.service.protocol import (
    ARGS_MODELS,
    MAX_MESSAGE_BYTES,
    PROTOCOL_VERSION,
    ErrorCode,
    ErrorInfo,
    Reply,
    Request,
)
from rigd.core.errors import ConfigError, DeviceError, TakeError

log = logging.getLogger(__name__)


class RequestError(Exception):
    def __init__(self, code: ErrorCode, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.info = ErrorInfo(code=code, message=message, field=field)


def _loc(prefix: str, loc: tuple[int | str, ...]) -> str:
    return ".".join([prefix, *(str(x) for x in loc)]) if prefix else ".".join(str(x) for x in loc)


def reply_bytes(reply: Reply) -> bytes:
    return reply.model_dump_json(exclude_none=True).encode()


def error_info(exc: Exception) -> ErrorInfo:
    """The structured error a failed request is answered with (call inside `except`)."""
    if isinstance(exc, RequestError):
        return exc.info
    for kind, code in _ERROR_CODES:
        if isinstance(exc, kind):
            return ErrorInfo(code=code, message=str(exc))
    log.error("request handler failed", exc_info=exc)
    return ErrorInfo(code="internal", message=f"{type(exc).__name__}: {exc}")


_ERROR_CODES: tuple[tuple[type[Exception], ErrorCode], ...] = (
    (ConfigError, "config_error"),
    (DeviceError, "device_error"),
    (TakeError, "take_error"),
)


def split_envelope(frames: list[bytes]) -> tuple[list[bytes], list[bytes]]:
    """ROUTER framing: routing ids up to the empty delimiter a REQ peer adds, then the body
    (a DEALER peer may send no delimiter: then the first frame is its id)."""
    try:
        cut = frames.index(b"", 1) + 1
    except ValueError:
        cut = 1
    return frames[:cut], frames[cut:]


def decode_request(frames: list[bytes]) -> dict[str, Any]:
    """The request body as a JSON object; `RequestError` says what is wrong with it."""
    if len(frames) != 1:
        raise RequestError("bad_request", f"a request is one message frame, got {len(frames)}")
    raw = frames[0]
    if len(raw) > MAX_MESSAGE_BYTES:
        raise RequestError("bad_request", f"request of {len(raw)} bytes; the limit is {MAX_MESSAGE_BYTES}")
    try:
        data = json.loads(raw.decode("utf-8"), object_pairs_hook=_object_no_duplicates)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RequestError("bad_json", f"request is not UTF-8 JSON: {exc}") from None
    except RecursionError:
        raise RequestError("bad_json", "request JSON is nested too deeply") from None
    if not isinstance(data, dict):
        raise RequestError("bad_json", f"a request is a JSON object, got {type(data).__name__}")
    if (where := _first_duplicate(data)) is not None:
        raise RequestError("bad_request", f"duplicate key {where!r} in the request", where)
    return data


class _DuplicateKeys(dict[str, Any]):
    """A JSON object that named `duplicate` more than once (which value wins is up to the
    parser, so such a request is refused rather than guessed at)."""

    duplicate: str = ""


def _object_no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """`object_pairs_hook` for json.loads: marks objects with a repeated key.

    The hook cannot know where its object sits, so it marks it and `_first_duplicate` finds
    the path afterwards, for an error that names the field."""
    obj = dict(pairs)
    if len(obj) == len(pairs):
        return obj
    seen: set[str] = set()
    marked = _DuplicateKeys(obj)
    for key, _ in pairs:
        if key in seen:
            marked.duplicate = key
            break
        seen.add(key)
    return marked


def _first_duplicate(data: Any) -> str | None:
    """Dotted path of the first repeated key anywhere in a parsed request, or None.

    Iterative: a request nested as deeply as json.loads allows must not overflow the stack."""
    stack: list[tuple[str, Any]] = [("", data)]
    while stack:
        prefix, node = stack.pop()
        if isinstance(node, _DuplicateKeys):
            return f"{prefix}.{node.duplicate}" if prefix else node.duplicate
        if isinstance(node, dict):
            items: list[tuple[str, Any]] = list(node.items())
        elif isinstance(node, list):
            items = [(str(i), v) for i, v in enumerate(node)]
        else:
            continue
        for key, value in reversed(items):
            stack.append((f"{prefix}.{key}" if prefix else key, value))
    return None


def validate_request(data: dict[str, Any]) -> tuple[str, BaseModel]:
    """The command and its validated arguments."""
    v = data.get("v")
    if isinstance(v, int) and not isinstance(v, bool) and v != PROTOCOL_VERSION:
        raise RequestError(
            "unsupported_version",
            f"protocol version {v} is not spoken here (this daemon: {PROTOCOL_VERSION})",
            "v",
        )
    try:
        req = Request.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        raise RequestError("bad_request", err["msg"], _loc("", err["loc"]) or None) from None
    model = ARGS_MODELS.get(req.cmd)
    if model is None:
        raise RequestError(
            "unknown_command", f"unknown command {req.cmd!r} (known: {', '.join(ARGS_MODELS)})", "cmd"
        )
    try:
        args = model.model_validate(req.args)
    except ValidationError as exc:
        err = exc.errors()[0]
        raise RequestError("bad_request", err["msg"], _loc("args", err["loc"])) from None
    return req.cmd, args
