# ruff: noqa: N803, N806  (K, R, t follow the notation of the calibration literature)
"""What every export format shares: calibrated cameras, undistortion and resizing, the frame
table (one timestep per trigger pulse seen by every camera), the train/test split, times.

Why one plan for all formats: the trainer formats must agree to the microsecond and the
micrometre (same camera centres, same times, same split), so they are all written from the same
`ExportPlan` and differ only in file layout and axis conventions.

Conventions (docs/export.md):
- World frame = the rig frame of the calibration: x_cam = R x_world + t (OpenCV axes, metres).
- Undistortion: a camera with all-zero `dist` keeps its K and its pixels untouched; otherwise
  the new K is cv2.getOptimalNewCameraMatrix(alpha=0, centerPrincipalPoint=True): only valid
  pixels, principal point at the image centre (what D-NeRF-style loaders assume).
- Resize: pixel centres at integers, so u' = (u + 0.5) s - 0.5: fx' = fx s, cx' = (cx + 0.5) s - 0.5.
- Time of a frame: mid-exposure on the rig timebase, t_exposure_start_us + exposure_us // 2.
- Split: timestep k (pulses counted from the first exported one) is train when k is even, test
  when odd: training at 15 of 30 FPS with the odd frames held out, as in the paper.
"""

from __future__ import annotations

import logging
import os
import re
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Protocol

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from rigd.core.errors import ConfigError, TakeError
from rigd.core.layout import Frames, frame_group
from rigd.core.progress import ProgressCallback, ProgressUpdate
from rigd.products.export.outputs import write_image
from rigd.take.linked import open_take_h5
from rigd.take.reader import Take

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]

#: Threads that undistort, resize and encode frames (cv2 releases the GIL).
IMAGE_THREADS = min(4, os.cpu_count() or 1)


class PointCloudLike(Protocol):
    """What a plan keeps of its point cloud (rigd.products.export.points.PointCloud)."""

    xyz: F64

    def __len__(self) -> int: ...


#: Relative output path of (timestep k, camera j).
PathOf = Callable[[int, int], str]

FORMATS = ("dynamic3dgs", "4dgaussians", "nerfstudio", "colmap", "dsec", "mcap")
Format = Literal["dynamic3dgs", "4dgaussians", "nerfstudio", "colmap", "dsec", "mcap"]
#: Formats that need no calibration or RGB camera (every take's data, as it is stored).
UNCALIBRATED_FORMATS = ("mcap",)
WORLDS = ("board", "cam0", "floor")
World = Literal["board", "cam0", "floor"]
SPLITS = ("time", "camera")
Split = Literal["time", "camera"]

#: The world and split a format gets unless asked otherwise: Dynamic3DGaussians' floor loss needs
#: a gravity-aligned world with the floor at y = 0, and PanopticSports-style loaders (it and
#: 4DGaussians' reader of that layout) train and test on the same timesteps, split by camera.
DEFAULT_WORLD: dict[str, World] = {"dynamic3dgs": "floor", "4dgaussians": "cam0"}
DEFAULT_SPLIT: dict[str, Split] = {"dynamic3dgs": "camera", "4dgaussians": "camera"}

#: Where a consumer puts the centre of pixel (0, 0): rigd (OpenCV) at 0; COLMAP, nerfstudio
#: (pixel_offset 0.5) and the diff-gaussian-rasterization projection of Dynamic3DGaussians and
#: 4DGaussians at 0.5, so their principal point is rigd's plus 0.5.
PIXEL_CENTRE = {"opencv": 0.0, "colmap": 0.5, "nerfstudio": 0.5, "gaussians": 0.5}

#: OpenCV -> OpenGL camera axes (x right, y up, z backwards): flip y and z.
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


class ExportOptions(BaseModel):
    """What `rigd export` writes, validated before anything is read."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    take: Path = Field(description="Take file (.h5) with a stored calibration.")
    format: Format = Field(description="Output layout: " + ", ".join(FORMATS) + ".")
    out: Path = Field(description="Output directory (created; its parent must exist).")
    resize: tuple[int, int] | None = Field(None, description="Output image size (W, H); intrinsics scaled.")
    segments: Path | None = Field(
        None, description="`rigd reconstruct` output dir: copy <take_id>/**/segments.json if present."
    )
    voxel_bins: int = Field(5, ge=1, description="Time bins of the per-frame event voxel grids.")
    point_frames: int = Field(
        6, ge=1, le=1000, description="Timesteps used to triangulate the initial point cloud."
    )
    seg: bool = Field(
        False, description="Kept for old command lines: dynamic3dgs always writes its seg/ masks now."
    )
    world: World | None = Field(
        None,
        description="World frame: board plane, cam0 (the rig frame), floor (gravity-aligned, floor y=0).",
    )
    split: Split | None = Field(None, description="Hold out odd timesteps (time) or a camera (camera).")
    test_cameras: tuple[str, ...] = Field(
        (), description="--split camera: the held-out cameras (default: the middle camera of the rig)."
    )
    jpeg_quality: int = Field(95, ge=50, le=100, description="JPEG quality where a format needs JPEG.")
    force: bool = Field(False, description="Replace an earlier export (or its leftovers) at `out`.")
    ros_epoch: Literal["take", "rig"] = Field(
        "take", description="mcap: stamps are rig time + the take's creation second (take) or rig time (rig)."
    )
    ros_slice_us: int = Field(
        0, ge=0, description="mcap: merge stored event blocks into packets of this span (0: one per block)."
    )
    compressed: bool = Field(False, description="mcap: frames as PNG sensor_msgs/CompressedImage.")
    ros_compression: Literal["zstd", "lz4", "none"] = Field(
        "zstd", description="mcap: chunk compression (lz4: faster, larger; none: fastest)."
    )

    @field_validator("format", mode="before")
    @classmethod
    def _known_format(cls, v: object) -> object:
        if v not in FORMATS:
            raise ValueError(f"unknown format {v!r} (one of {', '.join(FORMATS)})")
        return v

    @model_validator(mode="after")
    def _mcap_takes_no_layout_knobs(self) -> ExportOptions:
        """The trainer layouts' knobs mean nothing to `mcap` (it writes the take's streams as
        stored): one given with it is refused, not ignored."""
        if self.format not in UNCALIBRATED_FORMATS:
            return self
        defaults = type(self).model_fields
        knobs = ("resize", "segments", "voxel_bins", "point_frames", "world", "split", "test_cameras")
        given = [
            f"--{k.replace('_', '-')}"
            for k in (*knobs, "jpeg_quality")
            if getattr(self, k) != defaults[k].default
        ]
        if given:
            raise ValueError(
                f"{', '.join(given)}: not an option of --format {self.format}, which writes the take's "
                "streams as stored (frames as their mosaics, events as their words, no voxel grids)"
            )
        return self

    @property
    def world_frame(self) -> World:
        return self.world or DEFAULT_WORLD.get(self.format, "cam0")

    @property
    def split_kind(self) -> Split:
        return self.split or DEFAULT_SPLIT.get(self.format, "time")


def K_at(K: F64, centre: float) -> F64:  # noqa: N802
    """K in a convention whose pixel (0, 0) is centred at `centre` (rigd's K has it at 0)."""
    out = np.asarray(K, np.float64).copy()
    out[0, 2] += centre
    out[1, 2] += centre
    return out


#: Digits a whole-number knob may have (int64; Python refuses to parse over 4300 digits).
_MAX_DIGITS = 18


def shown(text: str) -> str:
    """A knob's value as quoted in an error line, cut short when it is long."""
    return repr(text if len(text) <= 40 else text[:37] + "...")


def parse_size(text: str) -> tuple[int, int]:
    """`WxH` -> (W, H) in ASCII digits; a ConfigError names the bad text. The bounds of the size
    depend on the take and the machine (`rigd.products.export.bounds`)."""
    m = re.fullmatch(r"([0-9]+)[xX]([0-9]+)", text.strip())
    if m is None:
        raise ConfigError(f"--resize {shown(text)}: expected WxH with whole numbers >= 1, e.g. 1280x720")
    if max(len(m[1]), len(m[2])) > _MAX_DIGITS:
        raise ConfigError(f"--resize {shown(text)}: too large (more than {_MAX_DIGITS} digits)")
    w, h = int(m[1]), int(m[2])
    if w < 1 or h < 1:
        raise ConfigError(f"--resize {shown(text)}: expected WxH with whole numbers >= 1, e.g. 1280x720")
    return w, h


def parse_count(flag: str, text: str) -> int:
    """A whole number >= 1 in ASCII digits (not nan, inf, 1e3 or -1); a ConfigError names the flag."""
    t = text.strip()
    if re.fullmatch(r"\+?[0-9]+", t) is None:
        raise ConfigError(f"{flag} {shown(text)}: expected a whole number >= 1")
    if len(t.lstrip("+")) > _MAX_DIGITS:
        raise ConfigError(f"{flag} {shown(text)}: too large (more than {_MAX_DIGITS} digits)")
    if int(t) < 1:
        raise ConfigError(f"{flag} {shown(text)}: expected a whole number >= 1")
    return int(t)


@dataclass
class Camera:
    """One calibrated view as exported: the new pinhole K at the output size and its world pose."""

    name: str
    K: F64
    size: tuple[int, int]
    R: F64
    t: F64
    K_src: F64
    dist: F64
    size_src: tuple[int, int]
    maps: tuple[NDArray[np.float32], NDArray[np.float32]] | None = None

    @property
    def w2c(self) -> F64:
        """4x4 world -> camera, OpenCV axes."""
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = self.R, self.t
        return m

    @property
    def c2w_gl(self) -> F64:
        """4x4 camera -> world with OpenGL camera axes (nerfstudio, NeRF, D-NeRF)."""
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = self.R.T, self.centre
        return m @ CV_TO_GL

    @property
    def centre(self) -> F64:
        return -self.R.T @ self.t

    def process(self, image: NDArray[np.generic]) -> U8:
        """Raw frame -> undistorted, resized, 3-channel uint8 RGB."""
        img = np.asarray(image)
        if img.dtype != np.uint8:
            raise TakeError(f"camera {self.name}: frames of dtype {img.dtype}; export writes 8-bit images")
        if img.ndim == 2:
            img = np.repeat(img[:, :, None], 3, axis=2)
        elif img.shape[2] == 4:
            img = img[:, :, :3]
        if self.maps is not None:
            img = cv2.remap(img, self.maps[0], self.maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        if img.shape[1::-1] != self.size:
            img = cv2.resize(img, self.size, interpolation=cv2.INTER_AREA)
        return np.ascontiguousarray(img)


def pinhole_for(
    K: F64, dist: F64, size_src: tuple[int, int], size_out: tuple[int, int] | None
) -> tuple[F64, tuple[NDArray[np.float32], NDArray[np.float32]] | None]:
    """(new K at the output size, undistortion maps at the source size or None when dist is zero)."""
    maps: tuple[NDArray[np.float32], NDArray[np.float32]] | None = None
    K_new = np.asarray(K, np.float64).copy()
    if np.any(np.asarray(dist) != 0):
        K_opt, _ = cv2.getOptimalNewCameraMatrix(K, dist, size_src, 0.0, size_src, True)
        K_new = np.asarray(K_opt, np.float64)
        mx, my = cv2.initUndistortRectifyMap(K, dist, None, K_new, size_src, cv2.CV_32FC1)
        maps = (np.asarray(mx, np.float32), np.asarray(my, np.float32))
    if size_out is not None and tuple(size_out) != tuple(size_src):
        sx, sy = size_out[0] / size_src[0], size_out[1] / size_src[1]
        S = np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1.0]])
        K_new = S @ K_new
    return np.asarray(K_new, np.float64), maps


def missing_calibration_hint(take: Path, what: str) -> str:
    return (
        f"{take}: {what}; calibrate it into the take first: `rigd calibrate rig {take} --board SPEC "
        f"--out rig.json --into-take {take}` (add --events to include the event sensors)"
    )


def cameras_of(take: Take, resize: tuple[int, int] | None) -> list[Camera]:
    """The take's RGB cameras as calibrated; refuses a take whose cameras lack K or pose."""
    calib = take.calibration
    if not calib:
        raise TakeError(missing_calibration_hint(take.path, "no calibration stored"))
    lacking = [c for c in take.cameras if not {"K", "dist", "R", "t"} <= set(calib.get(c, {}))]
    if lacking:
        raise TakeError(missing_calibration_hint(take.path, f"no intrinsics and rig pose for {lacking}"))
    out = []
    for name in take.cameras:
        c = calib[name]
        shape = take.camera(name).shape
        size_src = (int(shape[1]), int(shape[0]))
        if tuple(int(v) for v in c["image_size"]) != size_src:
            raise TakeError(
                f"{take.path}: calibration of {name} is for {tuple(c['image_size'])}, frames are {size_src}"
            )
        K_new, maps = pinhole_for(c["K"], c["dist"], size_src, resize)
        out.append(
            Camera(
                name=name,
                K=K_new,
                size=resize or size_src,
                R=np.asarray(c["R"], np.float64).reshape(3, 3),
                t=np.asarray(c["t"], np.float64).reshape(3),
                K_src=np.asarray(c["K"], np.float64),
                dist=np.asarray(c["dist"], np.float64).ravel(),
                size_src=size_src,
                maps=maps,
            )
        )
    return out


@dataclass
class FrameTable:
    """Timesteps (trigger pulses seen by every camera) and, per camera, frame index and time."""

    pulses: NDArray[np.int64]  # (T,)
    index: NDArray[np.int64]  # (T, C) frame index in the take
    t_us: NDArray[np.int64]  # (T, C) mid-exposure, rig us
    exposure_us: NDArray[np.int64]  # (T, C)
    step: NDArray[np.int64] = field(init=False)  # (T,) pulses counted from the first exported one

    def __post_init__(self) -> None:
        self.step = self.pulses - self.pulses[0]

    @property
    def train(self) -> NDArray[np.bool_]:
        """Even timesteps train (15 of 30 FPS), odd ones are held out."""
        return self.step % 2 == 0

    @property
    def t0_us(self) -> int:
        return int(self.t_us.min())

    @property
    def t1_us(self) -> int:
        return int(self.t_us.max())

    @property
    def span_us(self) -> tuple[int, int]:
        """First exposure start to last exposure end: the events kept."""
        start = self.t_us - self.exposure_us // 2
        return int(start.min()), int((start + self.exposure_us).max())

    def time01(self) -> NDArray[np.float64]:
        """(T, C) times in [0, 1] over the exported frames."""
        return (self.t_us - self.t0_us) / max(self.t1_us - self.t0_us, 1)

    @property
    def step_times_us(self) -> NDArray[np.int64]:
        """(T,) one time per timestep: the mean over the cameras (they share the trigger)."""
        return np.round(self.t_us.mean(axis=1)).astype(np.int64)


def _frame_series(
    path: Path, cameras: Sequence[str]
) -> dict[str, tuple[NDArray[np.int64], NDArray[np.int64]]]:
    """(pulse_index, exposure_us) per camera, each read whole with plain h5py (the documented
    `/frames/<cam>` series): indexing frames one by one would read every image too."""
    with open_take_h5(path) as f:  # a joined take's cameras live in their hosts' parts
        return {
            c: (
                np.asarray(f[f"{frame_group(c)}/{Frames.PULSE_INDEX}"][()], np.int64),
                np.asarray(f[f"{frame_group(c)}/{Frames.EXPOSURE}"][()], np.int64),
            )
            for c in cameras
        }


def frame_table(take: Take, cameras: Sequence[str]) -> FrameTable:
    """Join the cameras' frames on their trigger pulse; pulses some camera missed are dropped."""
    pulses: NDArray[np.int64] | None = None
    per: dict[str, tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]] = {}
    series = _frame_series(take.path, cameras)
    for cam in cameras:
        fs = take.camera(cam)
        if len(fs) == 0:
            raise TakeError(f"{take.path}: camera {cam!r} has no frames")
        p, exp = (a[: len(fs)] for a in series[cam])
        per[cam] = (p, fs.timestamps_us + exp // 2, exp)
        ok = p[p >= 0]
        pulses = ok if pulses is None else np.intersect1d(pulses, ok)
    assert pulses is not None
    pulses = np.unique(pulses)
    if pulses.size == 0:
        raise TakeError(f"{take.path}: no trigger pulse has a frame from every camera {list(cameras)}")
    idx = np.empty((pulses.size, len(cameras)), np.int64)
    t = np.empty_like(idx)
    e = np.empty_like(idx)
    for j, cam in enumerate(cameras):
        p, tm, exp = per[cam]
        order = np.argsort(p, kind="stable")
        k = order[np.searchsorted(p[order], pulses)]
        idx[:, j], t[:, j], e[:, j] = k, tm[k], exp[k]
        dropped = int(np.count_nonzero(p >= 0)) - pulses.size
        if dropped:
            log.warning("%s: %d frames without a frame of every other camera are not exported", cam, dropped)
    return FrameTable(pulses=pulses, index=idx, t_us=t, exposure_us=e)


def test_camera_positions(options: ExportOptions, names: Sequence[str]) -> list[int]:
    """Positions of `--split camera`'s held-out cameras (default: the middle camera of the rig);
    a ConfigError for a name that is no camera, every camera, or --test-camera without the split."""
    asked = options.test_cameras
    if asked and options.split_kind != "camera":
        raise ConfigError(f"--test-camera {', '.join(asked)}: needs --split camera (the split is by time)")
    if not asked:
        return [len(names) // 2]
    unknown = [n for n in asked if n not in names]
    if unknown:
        raise ConfigError(
            f"--test-camera {', '.join(unknown)}: not a camera of the take ({', '.join(names)})"
        )
    if len(set(asked)) == len(names):
        raise ConfigError("--test-camera: every camera held out leaves nothing to train on")
    return [names.index(n) for n in asked]


@dataclass
class ExportPlan:
    """Everything the format writers need, read once from the take."""

    options: ExportOptions
    take: Take
    cameras: list[Camera]
    frames: FrameTable
    progress: ProgressCallback
    out: Path
    """Where the files go: the staging directory, renamed to options.out when complete."""
    world_note: str = "the rig frame of the stored calibration (cam0)"
    """What the world frame of the export is (export.json, logs)."""
    cloud: PointCloudLike | None = None
    """The initial point cloud in the export's world, once triangulated (`points.cloud_of`)."""
    rig_to_world: F64 = field(default_factory=lambda: np.eye(4))
    """x_world = rig_to_world @ x_rig (homogeneous): the transform applied to every pose."""

    def world_pose(self, R: F64, t: F64) -> tuple[F64, F64]:
        """A device's rig pose (x_cam = R x_rig + t) in the export's world."""
        A, b = self.rig_to_world[:3, :3], self.rig_to_world[:3, 3]
        R_w = np.asarray(R, np.float64) @ A.T
        return R_w, np.asarray(t, np.float64).reshape(3) - R_w @ b

    @property
    def test_cameras(self) -> list[int]:
        """Positions of the held-out cameras of `--split camera`."""
        return test_camera_positions(self.options, [c.name for c in self.cameras])

    @property
    def train_mask(self) -> NDArray[np.bool_]:
        """(T, C): does view (timestep k, camera j) train? `--split time`: the even timesteps;
        `--split camera`: every camera but the held-out ones, at every timestep."""
        T, C = self.frames.index.shape
        if self.options.split_kind == "time":
            return np.repeat(self.frames.train[:, None], C, axis=1)
        mask = np.ones((T, C), bool)
        mask[:, self.test_cameras] = False
        return mask

    def images(self) -> int:
        return int(self.frames.index.size)

    def write_images(self, path_of: PathOf, stage: str = "images") -> None:
        """Write every exported frame through `path_of(timestep, camera)`, reporting progress.

        Frames are read here (HDF5 reads are serialised anyway) and undistorted, resized and
        encoded on a few threads: cv2 releases the GIL, and encoding is most of the time."""
        total, done = self.images(), 0
        jobs: deque[Future[None]] = deque()

        def finish_oldest() -> None:
            nonlocal done
            jobs.popleft().result()  # re-raises a failed write here
            done += 1
            if done % 10 == 0 or done == total:
                self.progress(ProgressUpdate(stage, f"{done}/{total} frames", done, total))

        with ThreadPoolExecutor(max_workers=IMAGE_THREADS) as pool:
            for j, cam in enumerate(self.cameras):
                fs = self.take.camera(cam.name)
                for k in range(self.frames.pulses.size):
                    dest = self.out / path_of(k, j)
                    dest.parent.mkdir(parents=True, exist_ok=True)
                    raw = fs[int(self.frames.index[k, j])].image
                    jobs.append(pool.submit(self._write_one, cam, raw, dest))
                    while len(jobs) > 2 * IMAGE_THREADS or (jobs and jobs[0].done()):
                        finish_oldest()
            while jobs:
                finish_oldest()

    def _write_one(self, cam: Camera, raw: NDArray[np.generic], dest: Path) -> None:
        img = np.asarray(cv2.cvtColor(cam.process(raw), cv2.COLOR_RGB2BGR), np.uint8)
        jpeg = dest.suffix.lower() in (".jpg", ".jpeg")
        params = [cv2.IMWRITE_JPEG_QUALITY, self.options.jpeg_quality] if jpeg else []
        write_image(dest, img, params)

    def image(self, k: int, j: int) -> U8:
        """Exported (undistorted, resized) RGB image of timestep k, camera j."""
        cam = self.cameras[j]
        return cam.process(self.take.camera(cam.name)[int(self.frames.index[k, j])].image)
