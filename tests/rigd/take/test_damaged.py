"""Files a failed write left with a header that records an end before the data it refers to
("addr overflow"): inspect, recover and the reader say so in one line."""

from __future__ import annotations

import shutil
import struct
from pathlib import Path

import h5py
import pytest
from typer.testing import CliRunner

from rigd.app.cli import app
from rigd.app.testing.crash import append_step, open_writer
from rigd.core.errors import TakeFormatError
from rigd.take import Take, find_unfinished, recover_take
from rigd.take.recover import needs_recovery

#: Byte offset of the end-of-file address in a version 0 superblock (8-byte addresses).
_SB0_EOF = 40


def _overflowed(tmp_path: Path, eoa: int) -> Path:
    src = tmp_path / "src.h5"
    w = open_writer(src)
    for k in range(5):
        append_step(w, k)
    w.flush()
    w.close()
    p = tmp_path / "of.h5"
    shutil.copy(src, p)
    src.unlink()
    with p.open("r+b") as fh:
        fh.seek(_SB0_EOF)
        assert struct.unpack("<Q", fh.read(8))[0] > eoa
        fh.seek(_SB0_EOF)
        fh.write(struct.pack("<Q", eoa))
    return p


@pytest.mark.slow
@pytest.mark.parametrize("eoa", [2000, 8000])
def test_addr_overflow_is_one_line(tmp_path: Path, eoa: int) -> None:
    p = _overflowed(tmp_path, eoa)
    want = f"header records the file ending at byte {eoa}"
    with pytest.raises(TakeFormatError, match=want):
        Take(p)
    with pytest.raises(TakeFormatError, match=want):
        recover_take(p)
    with pytest.raises(TakeFormatError, match=want):
        recover_take(p, dry_run=True)
    with pytest.raises(TakeFormatError, match=want):
        needs_recovery(p)
    assert find_unfinished(tmp_path) == []  # skipped with a log line
    for args in ((), ("--json",)):
        res = CliRunner().invoke(app, ["inspect", str(p), *args])
        assert res.exit_code == 2
        assert want in res.output
        assert "Traceback" not in res.output


def test_unopenable_device_group_is_one_line(tmp_path: Path) -> None:
    """A device group listed in the file as a dangling soft link: refused by the structure check."""
    p = tmp_path / "g.h5"
    w = open_writer(p)
    append_step(w, 0)
    w.flush()
    w.close()
    with h5py.File(p, "r+") as f:
        f["events/ev1"] = h5py.SoftLink("/nowhere")
    with pytest.raises(TakeFormatError, match=r"/events/ev1: is a soft link \(to '/nowhere'\)"):
        recover_take(p, dry_run=True)
