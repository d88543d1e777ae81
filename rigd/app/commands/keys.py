"""`rigd keys`: a CurveZMQ key pair for a daemon or a client of one (docs/multi-host.md)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated

import typer

from rigd.app.commands.consoles import fail
from rigd.core.errors import ConfigError


def keys(
    name: Annotated[str, typer.Argument(help="Name of the pair: NAME.key (public), NAME.key_secret.")],
    out: Annotated[Path, typer.Option("--dir", help="Directory for the two files (created 0700).")] = Path(
        "keys"
    ),
) -> None:
    """Write a CurveZMQ key pair: the public half goes to the peers, the secret half stays (0600)."""
    import zmq.auth

    if not name or "/" in name or name.startswith("."):
        raise fail(ConfigError(f"keys: {name!r} is not a file name"))
    public, secret = out / f"{name}.key", out / f"{name}.key_secret"
    for p in (public, secret):
        if p.exists():
            raise fail(ConfigError(f"keys: {p} exists; a key is never overwritten (move it away first)"))
    try:
        out.mkdir(mode=0o700, parents=True, exist_ok=True)
        made_public, made_secret = zmq.auth.create_certificates(str(out), name)
        os.chmod(made_secret, 0o600)
    except OSError as exc:
        raise fail(ConfigError(f"keys: cannot write into {out}: {exc.strerror}")) from exc
    typer.echo(f"public: {made_public}\nsecret: {made_secret}")
