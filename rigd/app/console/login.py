"""The console's login, kept for the operator next to the control socket.

Why a file there: the control socket lives in an owner-only (0700) runtime directory, so whoever
can drive the rig through it is exactly who may drive it through the console. The daemon writes
its console's address and secret into that directory (file mode 0600) once the console listens,
and removes it at exit; `rigd console-url` reads it back. Another local user can neither list the
directory nor read the file.
"""

from __future__ import annotations

import errno
import logging
import os
from pathlib import Path

from pydantic import BaseModel, ConfigDict, ValidationError

from rigd.app.config import runtime_dir
from rigd.app.service.endpoints import ipc_path, prepare_ipc_dir
from rigd.core.errors import ConfigError, RigdError

log = logging.getLogger(__name__)

LOGIN_FILE = "console-login.json"


class NoConsoleLoginError(RigdError):
    """No console login where it was looked for (no daemon, or one without a web console)."""


class ConsoleLogin(BaseModel):
    """What `rigd console-url` needs: the console's address, its secret, and whose it is."""

    model_config = ConfigDict(extra="forbid")

    url: str
    token: str
    pid: int

    @property
    def login_url(self) -> str:
        """Opening this sets the login cookie and lands on the dashboard (see `security.py`)."""
        return f"{self.url}?token={self.token}"


def login_path(control_endpoint: str) -> Path:
    """The login file of the daemon at `control_endpoint`: next to its IPC control socket, else in
    the runtime directory (a TCP control endpoint)."""
    sock = ipc_path(control_endpoint)
    return (sock.parent if sock is not None else runtime_dir()) / LOGIN_FILE


def write_login(path: Path, login: ConsoleLogin) -> None:
    """Write `login` owner-only (0600) in its owner-only directory, atomically (a reader never sees
    half a file; a file others could write into is not reused)."""
    prepare_ipc_dir(path)  # 0700, ours, not writable by others: the control socket's rules
    tmp = path.with_name(f".{path.name}.{os.getpid()}")
    tmp.unlink(missing_ok=True)
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            os.fchmod(f.fileno(), 0o600)  # whatever the umask
            f.write(login.model_dump_json())
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise ConfigError(f"cannot write the console login {path}: {exc.strerror}") from exc


def read_login(path: Path) -> ConsoleLogin:
    """The login in `path`; NoConsoleLoginError when there is none (or its daemon is gone),
    RigdError naming the file when it cannot be read."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise NoConsoleLoginError(
            f"no console login in {path.parent}: is `rigd serve` running there, with its web console?"
        ) from None
    except OSError as exc:
        why = "permission denied" if exc.errno in (errno.EACCES, errno.EPERM) else exc.strerror
        raise RigdError(
            f"cannot read the console login {path}: {why} (only the daemon's user may open its console)"
        ) from exc
    try:
        login = ConsoleLogin.model_validate_json(text)
    except ValidationError as exc:
        raise RigdError(f"{path}: not a console login file ({exc.errors()[0]['msg']})") from exc
    if not _alive(login.pid):
        raise NoConsoleLoginError(f"{path} is left from a daemon (pid {login.pid}) that is no longer running")
    return login


def remove_login(path: Path, token: str) -> None:
    """Remove the login file if it is still this console's (never another daemon's)."""
    try:
        if ConsoleLogin.model_validate_json(path.read_text(encoding="utf-8")).token == token:
            path.unlink()
    except FileNotFoundError:
        return
    except (OSError, ValidationError) as exc:
        log.warning("console login %s left in place: %s", path, exc)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # a process of another user: alive
    return True
