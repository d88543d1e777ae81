"""Every command against hostile inputs: empty, random, truncated and structurally damaged
files, a directory where a file belongs, a missing path. The check for each: exit code 1 or 2,
the problem named on stderr (the file's name in it), no traceback, and no take lost (a good
take beside the bad input is byte for byte the same afterwards)."""

from __future__ import annotations

import hashlib
import shutil
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from firmware_sim.testing.takes import make_take
from rigd.app.cli import app

pytestmark = pytest.mark.slow

Make = Callable[[Path, Path], Path]
"""(directory, a good take there) -> the hostile input."""


def _bytes(data: bytes, suffix: str) -> Make:
    def make(d: Path, good: Path) -> Path:
        p = d / f"bad{suffix}"
        p.write_bytes(data)
        return p

    return make


def _truncated(suffix: str) -> Make:
    def make(d: Path, good: Path) -> Path:
        p = d / f"cut{suffix}"
        data = good.read_bytes()
        p.write_bytes(data[: len(data) // 2])
        return p

    return make


def _damaged(dataset: str) -> Make:
    def make(d: Path, good: Path) -> Path:
        p = d / "damaged.h5"
        shutil.copy(good, p)
        with h5py.File(p, "a") as f:
            del f[dataset]
        return p

    return make


def _directory(d: Path, good: Path) -> Path:
    p = d / "adir.h5"
    p.mkdir()
    return p


def _missing(d: Path, good: Path) -> Path:
    return d / "nope.h5"


RANDOM = np.random.default_rng(7).integers(0, 256, 65536, dtype=np.uint8).tobytes()
INPUTS: dict[str, Make] = {
    "empty": _bytes(b"", ".h5"),
    "random": _bytes(RANDOM, ".h5"),
    "text": _bytes(b"not a take\n" * 20, ".h5"),
    "hdf5-header-only": _bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 600, ".h5"),
    "truncated": _truncated(".h5"),
    "damaged-events": _damaged("events/ev0/t"),
    "damaged-frames": _damaged("frames/cam0/t_exposure_start_us"),
    "damaged-index": _damaged("events/ev0/ms_to_idx"),
    "directory": _directory,
    "missing": _missing,
}
RAW_INPUTS: dict[str, Make] = {
    "empty": _bytes(b"", ".raw"),
    "random": _bytes(RANDOM, ".raw"),
    "bad-header": _bytes(b"% evt 3.0\n% format EVT3;width=abc;height=720\n% end\n" + RANDOM[:4096], ".raw"),
    "header-only": _bytes(b"% evt 3.0\n% format EVT3;width=1280;height=720\n% end\n", ".raw"),
    "dat-bad-header": _bytes(b"% Width abc\n% Height 720\n" + RANDOM[:4096], ".dat"),
    "directory": _directory,
    "missing": _missing,
}
CONFIG_INPUTS: dict[str, Make] = {
    "empty": _bytes(b"", ".toml"),
    "random": _bytes(RANDOM, ".toml"),
    "binary-json": _bytes(b"\xff\xfe{" + RANDOM[:256], ".json"),
    "yaml-junk": _bytes(b"cameras: [\n  - {name: \n", ".yaml"),
    "take-as-config": lambda d, good: good,
    "directory": _directory,
    "missing": _missing,
}

COMMANDS: dict[str, tuple[dict[str, Make], Callable[[Path, Path], list[str]]]] = {
    "inspect": (INPUTS, lambda p, d: ["inspect", str(p)]),
    "inspect --json": (INPUTS, lambda p, d: ["inspect", "--json", str(p)]),
    "inspect --thumbnails": (INPUTS, lambda p, d: ["inspect", str(p), "--thumbnails", str(d / "s.png")]),
    "convert take to raw": (INPUTS, lambda p, d: ["convert", str(p), str(d / "out.raw"), "--format", "evt3"]),
    "convert raw to take": (RAW_INPUTS, lambda p, d: ["convert", str(p), str(d / "out.h5")]),
    "capture --config": (
        CONFIG_INPUTS,
        lambda p, d: ["capture", "--local", "--config", str(p), "--duration", "1", "--out", str(d / "t")],
    ),
    "capture --replay": (
        INPUTS,
        lambda p, d: ["capture", "--replay", str(p), "--sim-clock", "virtual", "--out", str(d / "t")],
    ),
    "doctor --config": (CONFIG_INPUTS, lambda p, d: ["doctor", "--config", str(p)]),
    "serve --config": (CONFIG_INPUTS, lambda p, d: ["serve", "--config", str(p)]),
    "simulate-events": (INPUTS, lambda p, d: ["simulate-events", str(p), "--out", str(d / "sim.h5")]),
    "reconstruct": (INPUTS, lambda p, d: ["reconstruct", str(p), "--out", str(d / "rec")]),
    "calibrate events": (
        INPUTS,
        lambda p, d: [
            "calibrate",
            "events",
            str(p),
            "--sensor",
            "ev0",
            "--board",
            "chessboard:9x6:0.08",
            "--out",
            str(d / "ev0.yaml"),
        ],
    ),
    "calibrate intrinsics": (
        {**INPUTS, "png-junk": _bytes(RANDOM, ".png"), "png-empty": _bytes(b"", ".png")},
        lambda p, d: [
            "calibrate",
            "intrinsics",
            "--board",
            "chessboard:9x6:0.025",
            str(p),
            "--out",
            str(d / "cam.yaml"),
        ],
    ),
    "recover": (
        {k: v for k, v in INPUTS.items() if not k.startswith("damaged") and k != "directory"},
        lambda p, d: ["recover", str(p)],
    ),
}
CASES = [(cmd, kind) for cmd, (inputs, _) in COMMANDS.items() for kind in inputs]


def _digest(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


@pytest.mark.parametrize(("command", "kind"), CASES)
def test_hostile_input_is_one_clear_error_and_loses_nothing(tmp_path: Path, command: str, kind: str) -> None:
    inputs, argv = COMMANDS[command]
    good = tmp_path / "good.h5"
    make_take(good)
    before = _digest(good)
    bad = inputs[kind](tmp_path, good)
    result = CliRunner().invoke(app, argv(bad, tmp_path))
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    assert result.exit_code in (1, 2), (result.exit_code, result.output)
    assert "Traceback" not in result.output
    stderr = result.stderr
    assert bad.name in stderr or str(bad) in " ".join(stderr.split()), stderr
    assert _digest(good) == before  # the good take beside it is untouched
