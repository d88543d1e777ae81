"""Every `rigd ... --help` speaks one placeholder style: flags without one, values and arguments
upper case (PATH, FLOAT, TAKE), no Python types."""

from __future__ import annotations

import re

import pytest
import typer.main
from typer.testing import CliRunner

from rigd.app.cli import app

#: Typer's own labels, which name Python types.
PY_TYPES = re.compile(r"<(bool|str|int|float|path|list\[[^>]*\])>|list\[")
#: A usage placeholder: NAME, [NAME], NAME... or [NAME]...
PLACEHOLDER = re.compile(r"^\[?[A-Z][A-Z0-9_]*\]?(\.\.\.)?$")


def _commands() -> list[list[str]]:
    """The path of every command and group under `rigd`, the root included."""
    paths: list[list[str]] = []

    def walk(cmd: object, path: list[str]) -> None:
        paths.append(path)
        for name, sub in sorted(getattr(cmd, "commands", {}).items()):
            walk(sub, [*path, name])

    walk(typer.main.get_command(app), [])
    return paths


def test_every_command_is_walked() -> None:
    names = {" ".join(p) for p in _commands()}
    assert {"", "capture", "inspect", "calibrate", "calibrate events", "simulate-events", "serve"} <= names


@pytest.mark.slow
@pytest.mark.parametrize("path", _commands(), ids=lambda p: " ".join(p) or "rigd")
def test_help_uses_one_placeholder_style(path: list[str]) -> None:
    r = CliRunner().invoke(app, [*path, "--help"], prog_name="rigd", env={"COLUMNS": "200", "NO_COLOR": "1"})
    assert r.exit_code == 0, r.output
    text = r.stdout
    assert not PY_TYPES.search(text), PY_TYPES.search(text)
    usage = next(line for line in text.splitlines() if "Usage:" in line)
    pieces = usage.split("Usage:")[1].split()
    assert pieces[: len(path) + 1] == ["rigd", *path]
    rest = [p for p in pieces[len(path) + 1 :] if p not in ("[OPTIONS]", "COMMAND", "[ARGS]...")]
    for piece in rest:
        assert PLACEHOLDER.match(piece), f"{usage!r}: {piece!r}"
    assert "{" not in usage


def test_a_plain_typer_sub_app_gets_the_same_placeholders() -> None:
    import typer

    from rigd.app.commands.help import RigdTyper

    root = RigdTyper(no_args_is_help=True)
    sub = typer.Typer()

    @sub.command("go")
    def go(take: str, fast: bool = False, out: str = "x") -> None:
        """A command from another package."""

    @root.command("version")
    def version() -> None:
        """Keeps the root a group."""

    root.add_typer(sub, name="plugin")
    r = CliRunner().invoke(root, ["plugin", "go", "--help"], prog_name="rigd", env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    assert not PY_TYPES.search(r.stdout), r.stdout
    assert "rigd plugin go [OPTIONS] TAKE" in r.stdout
