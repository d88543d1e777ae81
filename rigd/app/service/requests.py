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
    """The reply as UTF-8 JSON; never raises.

    A reply holding text that is not valid Unicode (a file name that is not UTF-8 comes back
    from the file system as lone surrogates) cannot be encoded: it is answered with a
    structured error naming where the text was, instead of ending the control loop."""
    try:
        return reply.model_dump_json(exclude_none=True).encode()
    except ValueError as exc:  # PydanticSerializationError is a ValueError
        where = _first_problem(reply.model_dump()) or ("", "")
        log.error("reply to request %s cannot be encoded (%s at %s)", printable(reply.id), exc, where[0])
        fallback = Reply(
            id=None if reply.id is None else printable(reply.id),
            ok=False,
            error=ErrorInfo(
                code="internal",
                message=f"the reply could not be encoded as JSON: {where[1] or printable(str(exc))}"
                + (f" at {where[0]}" if where[0] else ""),
            ),
        )
        return fallback.model_dump_json(exclude_none=True).encode()


def printable(text: str | None) -> str:
    """`text` with anything UTF-8 cannot encode (lone surrogates) written as a backslash escape."""
    return "" if text is None else text.encode("utf-8", "backslashreplace").decode("utf-8")


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
    return parse_json_object(frames[0])


def parse_json_object(
    raw: bytes, what: str = "request", max_bytes: int = MAX_MESSAGE_BYTES
) -> dict[str, Any]:
    """`raw` as a JSON object, as strictly as the control socket reads requests; the web console
    reads its request bodies with it too, so both refuse the same input.

    Refused (`RequestError`, naming the field where it can): more than `max_bytes`, not UTF-8
    JSON, nested too deeply, not an object, a key repeated in one object (which value wins
    is up to the parser, so it is refused rather than guessed at), text that is not valid
    Unicode (a lone surrogate such as \\ud800 is valid JSON but cannot be encoded again, so
    it would break the reply), and integers of more than MAX_INT_DIGITS digits."""
    if len(raw) > max_bytes:
        raise RequestError("bad_request", f"{what} of {len(raw)} bytes; the limit is {max_bytes}")
    try:
        data = json.loads(raw.decode("utf-8"), object_pairs_hook=_object_no_duplicates, parse_int=_parse_int)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RequestError("bad_json", f"{what} is not UTF-8 JSON: {exc}") from None
    except RecursionError:
        raise RequestError("bad_json", f"{what} JSON is nested too deeply") from None
    if not isinstance(data, dict):
        raise RequestError("bad_json", f"a {what} is a JSON object, got {type(data).__name__}")
    problem = _first_problem(data)
    if problem is not None:
        where, message = problem
        raise RequestError("bad_request", f"{message} in the {what}", where or None)
    return data


#: Longest integer a request may hold: no field needs more, and beyond about 4300 digits
#: Python refuses to convert one at all (a ValueError that is no JSON error).
MAX_INT_DIGITS = 64


class _LongInt:
    """Stands for an integer literal of more than MAX_INT_DIGITS digits (refused after parsing,
    where its field can be named)."""

    def __init__(self, digits: int) -> None:
        self.digits = digits


def _parse_int(text: str) -> int | _LongInt:
    digits = len(text.lstrip("-"))
    return _LongInt(digits) if digits > MAX_INT_DIGITS else int(text)


class _DuplicateKeys(dict[str, Any]):
    """A JSON object that named `duplicate` more than once."""

    duplicate: str = ""


def _object_no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """`object_pairs_hook` for json.loads: marks objects with a repeated key.

    The hook cannot know where its object sits, so it marks it and `_first_problem` finds
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


def _bad_text(text: str) -> bool:
    if text.isascii():
        return False
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return True
    return False


def _first_problem(data: Any) -> tuple[str, str] | None:
    """(dotted path, what is wrong) of the first repeated key, over-long integer or text that
    is not valid Unicode (in a key or a value) anywhere in parsed JSON, or None.

    Iterative: a document nested as deeply as json.loads allows must not overflow the stack.
    Paths are printable (a bad key is written escaped)."""
    stack: list[tuple[str, Any]] = [("", data)]
    while stack:
        path, node = stack.pop()
        if isinstance(node, _DuplicateKeys):
            return _join(path, printable(node.duplicate)), f"duplicate key {printable(node.duplicate)!r}"
        if isinstance(node, _LongInt):
            return path, f"an integer of {node.digits} digits (at most {MAX_INT_DIGITS})"
        if isinstance(node, str):
            if _bad_text(node):
                return path, "text that is not valid Unicode (a lone surrogate)"
            continue
        if isinstance(node, dict):
            items: list[tuple[str, Any]] = []
            for key, value in node.items():
                key_text = str(key)
                if _bad_text(key_text):
                    return _join(
                        path, printable(key_text)
                    ), "a key that is not valid Unicode (a lone surrogate)"
                items.append((key_text, value))
        elif isinstance(node, list | tuple):
            items = [(str(i), v) for i, v in enumerate(node)]
        else:
            continue
        for key, value in reversed(items):
            stack.append((_join(path, key), value))
    return None


def _join(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


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
