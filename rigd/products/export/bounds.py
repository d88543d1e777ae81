"""Upper bounds of `rigd export`'s size knobs, from the formats and from what the machine has.

Why: `--resize 65536x65536` grew to 24 GB before the kernel killed it, and `--voxel-bins 100000`
ended in a numpy allocation error after the images were written. Every size is checked against
these bounds once the take is open and before anything is written; a refusal is one line that
names the flag, the size asked, the bound and what sets it.

The memory model is per output pixel (images) and per voxel (grids), measured (peak RSS of a
3-camera, 2-sensor take) and given a margin: nerfstudio at 3000x3000 peaked 80 MB above
1000x1000, about 10 bytes per pixel with 2 image threads; colmap (SIFT builds its float pyramid
on the image doubled in size to triangulate the point cloud) 1.9 GB above, about 245 bytes per
pixel; 2000 voxel bins of 320x180 1.3 GB above 5 bins, about 12 bytes per voxel. A knob may
plan with half of the available memory.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from rigd.core.errors import ConfigError

log = logging.getLogger(__name__)

#: Share of the available memory one export may plan to use.
MEMORY_SHARE = 0.5
#: Bytes per output pixel held by each image thread (frame, remapped, resized, BGR, encoded).
IMAGE_BYTES_PER_PX = 16
#: Bytes per output pixel of one SIFT pass (the Gaussian and DoG pyramids of the doubled image).
SIFT_BYTES_PER_PX = 320
#: Bytes per voxel of one grid being built and written (float64 sums, float32 grid, Zstd buffers).
VOXEL_BYTES = 24
#: Pixels of an image cv2.imread reads (CV_IO_MAX_IMAGE_PIXELS): a trainer could not load more.
MAX_IMAGE_PIXELS = 1 << 30
#: Largest side of a JPEG (libjpeg's JPEG_MAX_DIMENSION) and of an image cv2 reads (PNG).
MAX_SIDE = {"jpeg": 65_500, "png": 1 << 20}
#: Largest HDF5 chunk (one voxel grid is one chunk).
MAX_CHUNK_BYTES = (1 << 32) - 1
#: Formats whose images are JPEG (libjpeg bounds their side).
JPEG_FORMATS = ("dynamic3dgs", "4dgaussians", "colmap")
#: Formats that triangulate an initial point cloud with SIFT (dsec only with --world floor).
SIFT_FORMATS = ("dynamic3dgs", "4dgaussians", "colmap", "nerfstudio")


def _gb(n: float) -> str:
    return f"{n / 1e9:.1f} GB"


def _cgroup_available() -> int | None:
    """Bytes left under the cgroup v2 memory limit of this process, if it has one."""
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit == "max":
            return None
        return max(int(limit) - int(Path("/sys/fs/cgroup/memory.current").read_text()), 0)
    except (OSError, ValueError):
        return None


def available_memory() -> int:
    """Bytes this process may still allocate: the system's available memory (psutil when
    installed, else the free pages), capped by a cgroup limit."""
    try:
        import psutil

        avail = int(psutil.virtual_memory().available)
    except ImportError:
        avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    cg = _cgroup_available()
    return avail if cg is None else min(avail, cg)


@dataclass(frozen=True)
class Budget:
    """The memory an export may plan with, and the available memory it is a share of."""

    available: int

    @property
    def usable(self) -> int:
        return int(self.available * MEMORY_SHARE)

    def why(self) -> str:
        return f"{_gb(self.usable)} of the {_gb(self.available)} of available memory may be used"


def image_bytes_per_px(fmt: str, threads: int) -> int:
    """Peak bytes per output pixel of a format's image stage (the larger of encoding and SIFT)."""
    encode = threads * IMAGE_BYTES_PER_PX
    return max(encode, SIFT_BYTES_PER_PX) if fmt in SIFT_FORMATS else encode


def _refuse(asked: str, value: int, limits: list[tuple[int, str]]) -> None:
    """Raise naming the tightest of the limits that `value` exceeds (none exceeded: return)."""
    over = [(limit, why) for limit, why in limits if value > limit]
    if over:
        limit, why = min(over)
        raise ConfigError(f"{asked}: {why.format(limit=limit)}")


def check_resize(size: tuple[int, int], fmt: str, threads: int, budget: Budget) -> None:
    """Refuse an output size the format cannot store, a trainer cannot read, or memory cannot hold."""
    w, h = size
    asked = f"--resize {w}x{h}"
    kind = "jpeg" if fmt in JPEG_FORMATS else "png"
    side = MAX_SIDE[kind]
    _refuse(asked, max(w, h), [(side, f"a side of at most {{limit}} pixels: {fmt} writes {kind.upper()}")])
    px = w * h
    per_px = image_bytes_per_px(fmt, threads)
    by_memory = budget.usable // per_px
    scale = min(by_memory / px, 1.0) ** 0.5
    fit = f"{max(int(w * scale), 1)}x{max(int(h * scale), 1)}"
    _refuse(
        asked,
        px,
        [
            (
                MAX_IMAGE_PIXELS,
                f"{px} pixels per image, at most {{limit}} (2^30): cv2.imread reads no larger image "
                "(CV_IO_MAX_IMAGE_PIXELS)",
            ),
            (
                by_memory,
                f"{px} pixels per image, at most {{limit}} here (e.g. {fit}): {fmt} needs about {per_px} "
                f"bytes per output pixel ({_gb(px * per_px)}) and {budget.why()}",
            ),
        ],
    )


def check_voxel_bins(
    bins: int, geometry: dict[str, tuple[int, int]], windows_us: NDArray[np.int64], budget: Budget
) -> None:
    """Refuse a bin count finer than the microsecond clock, larger than an HDF5 chunk, or one
    whose grid does not fit the memory (checked for the largest event sensor)."""
    if not geometry:
        return  # no event sensor: no grid is written
    sensor, (w, h) = max(geometry.items(), key=lambda kv: kv[1][0] * kv[1][1])
    npx = w * h
    shortest = int(np.min(windows_us[:, 1] - windows_us[:, 0])) if windows_us.size else 1
    _refuse(
        f"--voxel-bins {bins}",
        bins,
        [
            (
                MAX_CHUNK_BYTES // (4 * npx),
                f"at most {{limit}} for {sensor} ({w}x{h}): one grid is one HDF5 chunk, at most 4 GiB, "
                f"and {bins} float32 bins take {_gb(4 * bins * npx)}",
            ),
            (
                budget.usable // (VOXEL_BYTES * npx),
                f"at most {{limit}} here for {sensor} ({w}x{h}): a grid takes about {VOXEL_BYTES} bytes "
                f"per bin and pixel while built and written ({_gb(VOXEL_BYTES * bins * npx)}) and "
                f"{budget.why()}",
            ),
            (
                max(shortest, 1),
                f"at most {{limit}}: the shortest window between timesteps is {shortest} us and a bin "
                "is at least 1 us (times are whole microseconds)",
            ),
        ],
    )
