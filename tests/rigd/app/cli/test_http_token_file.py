"""The console secret never goes on the command line (`ps` shows every process's arguments to
every user): `--http-token` is refused before anything starts; a file or the environment give it."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from rigd.app.cli import app
from rigd.app.commands.service import read_token_file
from rigd.core.errors import ConfigError


def test_a_token_on_the_command_line_is_refused_first(tmp_path: Path) -> None:
    r = CliRunner().invoke(
        app, ["serve", "--config", str(tmp_path / "none.toml"), "--http-token", "s3cret-of-twenty-chars"]
    )
    assert r.exit_code == 2
    assert "--http-token-file" in r.output
    assert "RIGD_HTTP_TOKEN" in r.output
    assert "s3cret" not in r.output
    assert "Traceback" not in r.output


def test_the_token_file_is_read_and_checked(tmp_path: Path) -> None:
    f = tmp_path / "token"
    f.write_text("  kept-in-a-file-0123456789\n")
    assert read_token_file(f) == "kept-in-a-file-0123456789"
    f.write_text("\n")
    with pytest.raises(ConfigError, match="is empty"):
        read_token_file(f)
    with pytest.raises(ConfigError, match="cannot be read"):
        read_token_file(tmp_path / "missing")


def test_serve_says_which_token_file_it_cannot_use(tmp_path: Path) -> None:
    r = CliRunner().invoke(app, ["serve", "--http", "0.0.0.0:0", "--http-token-file", str(tmp_path / "no")])
    assert r.exit_code == 2
    assert f"--http-token-file {tmp_path / 'no'}: cannot be read" in r.output
