"""`rigd export` against hostile knobs, unusable `--out` paths, a full disk and SIGKILL.

Each case checks: the exit code (2 refused input, 1 failed write), one line on stderr naming the
flag, no traceback, nothing left where the export would go (no `--out`, no staging directory),
and the take byte for byte the same afterwards."""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from rigd.app.cli import app
from rigd.core.errors import ConfigError
from rigd.products.export import bounds
from rigd.products.export.common import FORMATS, UNCALIBRATED_FORMATS, parse_count, parse_size
from rigd.take.reader import open_take

runner = CliRunner()
REPO = Path(__file__).resolve().parents[4]

#: Values of --voxel-bins no export accepts, and what the line says.
BAD_BINS = [
    ("0", "whole number >= 1"),
    ("-3", "whole number >= 1"),
    ("nan", "whole number >= 1"),
    ("inf", "whole number >= 1"),
    ("-inf", "whole number >= 1"),
    ("1e3", "whole number >= 1"),
    ("2.5", "whole number >= 1"),
    ("", "whole number >= 1"),
    ("\u00b2", "whole number >= 1"),
    ("5x5", "whole number >= 1"),
    ("9" * 30, "too large"),
    ("100000", "at most"),
]
#: Values of --resize no export accepts (every format), and what the line says.
BAD_RESIZE = [
    ("0x10", "expected WxH"),
    ("10x0", "expected WxH"),
    ("-5x5", "expected WxH"),
    ("nanxnan", "expected WxH"),
    ("infx1", "expected WxH"),
    ("1.5x2", "expected WxH"),
    ("10x", "expected WxH"),
    ("x", "expected WxH"),
    ("\u00b2x3", "expected WxH"),
    ("1e9x1", "expected WxH"),
    ("10x10x10", "expected WxH"),
    ("9" * 40 + "x1", "too large"),
    ("40000x40000", "at most"),
    ("1000000x1000000", "at most"),
    ("65536x65536", "at most"),
]
#: The trainer layouts (the knobs below are theirs; `mcap` writes the streams as stored).
LAYOUTS = [f for f in FORMATS if f not in UNCALIBRATED_FORMATS]
KNOB_CASES = [
    *[("--voxel-bins", v, why, LAYOUTS[i % len(LAYOUTS)]) for i, (v, why) in enumerate(BAD_BINS)],
    *[("--resize", v, why, LAYOUTS[i % len(LAYOUTS)]) for i, (v, why) in enumerate(BAD_RESIZE)],
    # the bounds differ per format: every layout refuses sizes over every bound
    *[("--voxel-bins", "100000", "at most", f) for f in LAYOUTS],
    *[("--resize", "65536x65536", "at most", f) for f in LAYOUTS],
    *[("--resize", "70000x10", "JPEG", f) for f in bounds.JPEG_FORMATS],
    # a layout's knob given to mcap is refused, not ignored
    *[
        (flag, value, "not an option of --format mcap", "mcap")
        for flag, value in (("--voxel-bins", "3"), ("--resize", "64x36"))
    ],
]


def _digest(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _tree(d: Path) -> dict[str, str]:
    """Every file under d (relative path -> sha256)."""
    return {str(p.relative_to(d)): _digest(p) for p in sorted(d.rglob("*")) if p.is_file()}


def _one_line(output: str, *needles: str) -> str:
    assert "Traceback" not in output, output
    lines = [ln for ln in output.splitlines() if ln.strip()]
    assert len(lines) == 1, output
    line = lines[0]
    assert line.startswith("error:"), output
    flat = " ".join(line.split())
    for n in needles:
        assert n in flat, (n, output)
    return line


def _leftovers(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if "rigd-" in p.name)


def _export(take: Path, out: Path, *args: str) -> tuple[int, str]:
    r = runner.invoke(app, ["export", str(take), "--out", str(out), *args])
    assert r.exception is None or isinstance(r.exception, SystemExit), r.exception
    return r.exit_code, r.output


@pytest.mark.slow
@pytest.mark.parametrize(("flag", "value", "why", "fmt"), KNOB_CASES)
def test_hostile_knob_is_one_line_and_writes_nothing(
    takes: tuple[Path, Path], tmp_path: Path, flag: str, value: str, why: str, fmt: str
) -> None:
    _, take = takes
    before = _digest(take)
    out = tmp_path / "o"
    code, output = _export(take, out, "--format", fmt, f"{flag}={value}")
    assert code == 2, output
    line = _one_line(output, flag, why)
    if why == "at most":  # the line names the size asked, the bound and what sets it
        assert re.search(r"at most \d+", line), line
        assert any(w in line for w in ("memory", "HDF5 chunk", "cv2.imread", "JPEG", "1 us")), line
    assert not out.exists()
    assert _leftovers(tmp_path) == []
    assert _digest(take) == before


@pytest.mark.parametrize(
    ("fmt", "args"),
    [
        ("nerfstudio", ["--resize", "4000x4000"]),
        ("colmap", ["--resize", "1600x1600"]),
        ("dsec", ["--voxel-bins", "1000"]),
    ],
)
def test_size_over_the_available_memory_is_refused(
    takes: tuple[Path, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, fmt: str, args: list[str]
) -> None:
    """With 1 GB available, half of it may be planned with: each of these needs more."""
    _, take = takes
    monkeypatch.setattr(bounds, "available_memory", lambda: 10**9)
    code, output = _export(take, tmp_path / "o", "--format", fmt, *args)
    assert code == 2, output
    _one_line(output, args[0], args[1], "0.5 GB of the 1.0 GB of available memory")
    assert not (tmp_path / "o").exists()
    assert _leftovers(tmp_path) == []


def _refusal(check: Callable[[], object]) -> str | None:
    """The ConfigError's line when check() refuses, None when it passes (any other error fails)."""
    try:
        check()
    except ConfigError as exc:
        return str(exc)
    return None


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(st.text(max_size=50))
def test_any_resize_text_is_a_size_or_names_the_flag(text: str) -> None:
    error = _refusal(lambda: parse_size(text))
    if error is None:
        w, h = parse_size(text)
        assert min(w, h) >= 1
        assert re.fullmatch(r"\s*0*" + str(w) + "[xX]0*" + str(h) + r"\s*", text)
    else:
        assert error.startswith("--resize ")
        assert "\n" not in error


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(st.one_of(st.text(max_size=30), st.integers().map(str), st.floats().map(str)))
def test_any_bins_text_is_a_count_or_names_the_flag(text: str) -> None:
    error = _refusal(lambda: parse_count("--voxel-bins", text))
    if error is None:
        n = parse_count("--voxel-bins", text)
        assert n >= 1
        assert re.fullmatch(r"\s*\+?0*" + str(n) + r"\s*", text)
    else:
        assert error.startswith("--voxel-bins ")
        assert "\n" not in error


@settings(max_examples=300, deadline=None)
@given(
    w=st.integers(1, 1 << 24),
    h=st.integers(1, 1 << 24),
    fmt=st.sampled_from(FORMATS),
    avail=st.integers(0, 1 << 40),
)
@pytest.mark.slow
def test_a_resize_passes_only_within_every_bound(w: int, h: int, fmt: str, avail: int) -> None:
    budget = bounds.Budget(avail)
    per_px = bounds.image_bytes_per_px(fmt, 2)
    side = bounds.MAX_SIDE["jpeg" if fmt in bounds.JPEG_FORMATS else "png"]
    fits = max(w, h) <= side and w * h <= bounds.MAX_IMAGE_PIXELS and w * h * per_px <= budget.usable
    error = _refusal(lambda: bounds.check_resize((w, h), fmt, 2, budget))
    assert (error is None) == fits, error
    if error is not None:
        assert error.startswith(f"--resize {w}x{h}: ")
        assert "at most" in error


@settings(max_examples=300, deadline=None)
@given(
    bins=st.integers(1, 1 << 40),
    w=st.integers(1, 4096),
    h=st.integers(1, 4096),
    window=st.integers(0, 10**7),
    avail=st.integers(0, 1 << 40),
)
@pytest.mark.slow
def test_voxel_bins_pass_only_within_every_bound(bins: int, w: int, h: int, window: int, avail: int) -> None:
    windows = np.array([[0, window]], np.int64)
    budget = bounds.Budget(avail)
    fits = (
        bins * w * h * 4 <= bounds.MAX_CHUNK_BYTES
        and bins * w * h * bounds.VOXEL_BYTES <= budget.usable
        and bins <= max(window, 1)
    )
    error = _refusal(lambda: bounds.check_voxel_bins(bins, {"ev0": (w, h)}, windows, budget))
    assert (error is None) == fits, error
    if error is not None:
        assert error.startswith(f"--voxel-bins {bins}: at most ")


# --- --out ------------------------------------------------------------------------------------------


def _file(d: Path) -> Path:
    (d / "notes.txt").write_text("not an export\n")
    return d / "notes.txt"


def _under_file(d: Path) -> Path:
    return _file(d) / "o"


def _other_files(d: Path) -> Path:
    (d / "o").mkdir()
    (d / "o" / "thesis.tex").write_text("mine\n")
    return d / "o"


OUT_CASES = [
    (lambda d: Path("/proc/rigd-export-test"), "cannot create a directory in /proc"),
    (_file, "is a file"),
    (_under_file, "is not a directory"),
    (lambda d: d / "missing" / "o", "does not exist"),
    (_other_files, "not an export"),
]


@pytest.mark.parametrize("force", [False, True])
@pytest.mark.parametrize(("make", "why"), OUT_CASES)
def test_unusable_out_is_one_line_and_writes_nothing(
    takes: tuple[Path, Path], tmp_path: Path, make: object, why: str, force: bool
) -> None:
    _, take = takes
    before = _digest(take)
    assert callable(make)
    out = make(tmp_path)
    listing = _tree(tmp_path)
    code, output = _export(take, out, "--format", "nerfstudio", *(["--force"] if force else []))
    assert code == 2, output
    _one_line(output, f"--out {out}", why)
    assert _tree(tmp_path) == listing  # nothing written, nothing removed
    assert _digest(take) == before


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a read-only directory")
def test_unwritable_parent_is_one_line(takes: tuple[Path, Path], tmp_path: Path) -> None:
    _, take = takes
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        code, output = _export(take, ro / "o", "--format", "nerfstudio")
    finally:
        ro.chmod(0o755)
    assert code == 2, output
    _one_line(output, "--out", "Permission denied")
    assert list(ro.iterdir()) == []


@pytest.mark.slow
def test_existing_exports_are_named_and_replaced_only_with_force(
    takes: tuple[Path, Path], tmp_path: Path
) -> None:
    _, take = takes
    out = tmp_path / "o"
    code, output = _export(take, out, "--format", "nerfstudio")
    assert code == 0, output
    first = _tree(out)
    code, output = _export(take, out, "--format", "dsec")
    assert code == 2, output
    _one_line(output, f"--out {out}", "holds a complete export (nerfstudio of", "pass --force")
    assert _tree(out) == first
    code, output = _export(take, out, "--format", "dsec", "--force")
    assert code == 0, output
    assert (out / "split.json").is_file()
    assert not (out / "transforms.json").exists()
    assert _leftovers(tmp_path) == []


@pytest.mark.slow
def test_incomplete_export_of_an_older_rigd_is_named(takes: tuple[Path, Path], tmp_path: Path) -> None:
    _, take = takes
    out = tmp_path / "o"
    (out / "images" / "cam0").mkdir(parents=True)
    (out / "images" / "cam0" / "000000.png").write_bytes(b"half")
    code, output = _export(take, out, "--format", "nerfstudio")
    assert code == 2, output
    _one_line(output, "incomplete export", "--force")
    code, output = _export(take, out, "--format", "nerfstudio", "--force")
    assert code == 0, output
    assert (out / "export.json").is_file()


# --- a full disk ---------------------------------------------------------------------------------------


def _cli(*args: str, driver: str | None = None) -> subprocess.Popen[str]:
    """`rigd ARGS` in a fresh interpreter (a crash is its exit code, not the test run's)."""
    cmd = [sys.executable, "-c", driver, *args] if driver else [sys.executable, "-m", "rigd.app.cli", *args]
    env = {**os.environ, "COLUMNS": "250"}
    return subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A mount point under tmp_path; the test mounts a tmpfs of its size there (root only)."""
    d = tmp_path / "disk"
    d.mkdir()
    yield d
    if os.path.ismount(d):
        subprocess.run(["umount", str(d)], check=True)


def _mount(d: Path, size_kb: int) -> None:
    if shutil.which("mount") is None:
        pytest.skip("no mount command to make a small tmpfs")
    r = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size_kb}k", "tmpfs", str(d)], capture_output=True, text=True
    )
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {r.stderr.strip()}")


@pytest.fixture(scope="module")
def full_sizes(takes: tuple[Path, Path], tmp_path_factory: pytest.TempPathFactory) -> dict[str, int]:
    """Bytes of a complete export per format, to size the small disks by."""
    _, take = takes
    root = tmp_path_factory.mktemp("full")
    sizes = {}
    for fmt in ("nerfstudio", "dsec"):
        code, output = _export(take, root / fmt, "--format", fmt)
        assert code == 0, output
        sizes[fmt] = sum(p.stat().st_size for p in (root / fmt).rglob("*") if p.is_file())
    return sizes


@pytest.mark.parametrize(
    ("fmt", "share"),
    [
        ("nerfstudio", 0.15),
        ("nerfstudio", 0.5),
        ("nerfstudio", 0.6),
        ("nerfstudio", 0.7),
        ("nerfstudio", 0.8),
        ("nerfstudio", 0.9),
        ("dsec", 0.3),
        ("dsec", 0.7),
        ("dsec", 0.9),
    ],
)
@pytest.mark.slow
def test_full_disk_is_one_line_and_leaves_nothing(
    takes: tuple[Path, Path], full_sizes: dict[str, int], small_disk: Path, fmt: str, share: float
) -> None:
    """The disk fills at a share of the export's size: in the images, the voxel grids, the events.
    It used to end in a segmentation fault (exit 139) when it filled while voxels.h5 was written."""
    _, take = takes
    before = _digest(take)
    _mount(small_disk, int(full_sizes[fmt] * share) // 1024)
    p = _cli("export", str(take), "--format", fmt, "--out", str(small_disk / "o"))
    _, stderr = p.communicate(timeout=280)
    assert p.returncode == 1, (p.returncode, stderr)
    _one_line(stderr, f"--out {small_disk / 'o'}", "No space left on device", "partial output was removed")
    assert list(small_disk.iterdir()) == []
    assert _digest(take) == before


@pytest.mark.slow
def test_export_fits_a_disk_of_its_size(
    takes: tuple[Path, Path], full_sizes: dict[str, int], small_disk: Path
) -> None:
    """The small disk itself works: an export of three times the space completes."""
    _, take = takes
    _mount(small_disk, 3 * full_sizes["nerfstudio"] // 1024)
    p = _cli("export", str(take), "--format", "nerfstudio", "--out", str(small_disk / "o"))
    _, stderr = p.communicate(timeout=280)
    assert p.returncode == 0, stderr
    assert sorted(x.name for x in small_disk.iterdir()) == ["o"]


#: `rigd ARGV[3:]` with os.pwrite failing (ENOSPC) for the file named ARGV[1] past offset ARGV[2].
FAILING_WRITES = """
import errno, os, sys
real, name, after = os.pwrite, sys.argv[1], int(sys.argv[2])
def pwrite(fd, data, offset):
    if os.readlink(f"/proc/self/fd/{fd}").endswith(name) and offset > after:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    return real(fd, data, offset)
os.pwrite = pwrite
from rigd.app.cli import main
sys.argv = ["rigd", *sys.argv[3:]]
main()
"""


@pytest.mark.parametrize(
    ("fmt", "name", "offset"),
    [
        ("nerfstudio", "voxels.h5", 0),
        ("nerfstudio", "voxels.h5", 50_000),
        ("dsec", "events.h5", 0),
        ("dsec", "events.h5", 20_000),
        ("dsec", "rectify_map.h5", 0),
    ],
)
@pytest.mark.slow
def test_failed_hdf5_write_is_one_line(
    takes: tuple[Path, Path], tmp_path: Path, fmt: str, name: str, offset: int
) -> None:
    """The write error injected where HDF5 writes, without a small disk."""
    _, take = takes
    out = tmp_path / "o"
    p = _cli(
        name, str(offset), "export", str(take), "--format", fmt, "--out", str(out), driver=FAILING_WRITES
    )
    _, stderr = p.communicate(timeout=280)
    assert p.returncode == 1, (p.returncode, stderr)
    _one_line(stderr, f"--out {out}", "No space left on device", name, "is not created")
    assert list(tmp_path.iterdir()) == []


# --- SIGKILL ----------------------------------------------------------------------------------------------

#: `rigd ARGV[3:]` that writes the file ARGV[1] and blocks (to be killed) at stage ARGV[2]: after the
#: fifth image, before the staging directory is renamed, or between the two renames of a --force.
BLOCKING = """
import os, sys, threading
from pathlib import Path
reached, stage = Path(sys.argv[1]), sys.argv[2]
def block():
    reached.write_text(stage)
    threading.Event().wait()
if stage == "images":
    from rigd.products.export import common
    real, n = common.ExportPlan._write_one, [0]
    def write_one(self, *a):
        real(self, *a)
        n[0] += 1
        if n[0] == 5:
            block()
    common.ExportPlan._write_one = write_one
elif stage == "rename":
    from rigd.products.export import staging
    staging.Staging.commit = lambda self: block()
else:
    real_replace = os.replace
    def replace(src, dst):
        if str(src).endswith(".rigd-partial"):
            block()
        real_replace(src, dst)
    os.replace = replace
from rigd.app.cli import main
sys.argv = ["rigd", *sys.argv[3:]]
main()
"""


def _wait_for(reached: Path, p: subprocess.Popen[str]) -> None:
    """Until the export reaches its blocking point (or ends, which fails the test)."""
    deadline = time.monotonic() + 280
    while not reached.exists():
        if p.poll() is not None:
            pytest.fail(f"the export ended before it was killed: {p.returncode} {p.communicate()}")
        assert time.monotonic() < deadline, "the export never reached the point to kill it"
        time.sleep(0.05)


@pytest.mark.parametrize(
    ("stage", "previous", "left"),
    [
        ("images", False, "did not finish"),
        ("rename", False, "did not finish"),
        ("images", True, "did not finish"),
        ("rename", True, "did not finish"),
        ("swap", True, "replacement was interrupted"),
    ],
)
@pytest.mark.slow
def test_killed_export_leaves_no_output_and_rerun_says_what_to_do(
    takes: tuple[Path, Path], tmp_path: Path, stage: str, previous: bool, left: str
) -> None:
    _, take = takes
    before = _digest(take)
    out = tmp_path / "exports" / "o"
    out.parent.mkdir()
    old: dict[str, str] = {}
    if previous:
        code, output = _export(take, out, "--format", "nerfstudio")
        assert code == 0, output
        old = _tree(out)
    reached = tmp_path / "reached"
    argv = ["export", str(take), "--format", "dsec", "--out", str(out), "--force"]
    p = _cli(str(reached), stage, *argv, driver=BLOCKING)
    try:
        _wait_for(reached, p)
        # While it writes, a second export to the same place is refused, --force or not.
        code, output = _export(take, out, "--format", "dsec", "--force")
        assert code == 2, output
        _one_line(output, f"--out {out}", "another rigd export is writing it now", f"pid {p.pid}")
    finally:
        p.kill()
        p.communicate(timeout=60)
    assert p.returncode == -9
    if previous and stage != "swap":
        assert _tree(out) == old  # the previous export, untouched
    else:
        assert not out.exists() or _tree(out) == {}
    code, output = _export(take, out, "--format", "dsec")
    assert code == 2, output
    _one_line(output, f"--out {out}", left, ".o.rigd-", "pass --force")
    code, output = _export(take, out, "--format", "dsec", "--force")
    assert code == 0, output
    assert (out / "export.json").is_file()
    assert (out / "split.json").is_file()
    assert _leftovers(out.parent) == []
    assert _digest(take) == before


# --- --segments ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "content",
    [
        "not json",
        '{"segments": [{"keyframe_us": NaN}]}',
        '{"segments": [{"keyframe_us": Infinity}]}',
        '{"segments": [{"keyframe_us": 1e400}]}',
        '{"segments": [{"keyframe_us": 1.5}]}',
        '{"segments": [{"keyframe_us": true}]}',
        '{"segments": [{"keyframe_us": 1000000000000000000000000000000}]}',
        '{"segments": [{}]}',
        '{"segments": [7]}',
        '{"segments": 5}',
        "[1, 2]",
        "\udcff",
    ],
)
@pytest.mark.slow
def test_hostile_segments_file_is_one_line(takes: tuple[Path, Path], tmp_path: Path, content: str) -> None:
    _, take = takes
    before = _digest(take)
    with open_take(take) as tk:
        take_id = tk.take_id
    seg = tmp_path / "recon" / take_id / "ev0" / "segments.json"
    seg.parent.mkdir(parents=True)
    seg.write_bytes(content.encode("utf-8", "surrogateescape"))
    out = tmp_path / "o"
    code, output = _export(take, out, "--format", "nerfstudio", "--segments", str(tmp_path / "recon"))
    assert code == 2, output
    _one_line(output, f"--segments {seg}")
    assert not out.exists()
    assert _leftovers(tmp_path) == []
    assert _digest(take) == before
