# ruff: noqa: N803, N806  (R, t, X follow the notation of the calibration literature)
"""The consumer check: rigd's exports of a simulated take loaded by the consumers' own code.

    python -m bench.consumers [--work DIR] [--only dsec,tonic,...] [--seconds 2]

Each consumer is installed into its own scratch venv under --work (outside the project):
nerfstudio and tonic from the registry, 4DGaussians, Dynamic3DGaussians and DSEC's EventSlicer
from the pinned commits below, cloned for the check (never copied into the project). The checks
(bench/consumer_checks/, run with the venv's python) call the consumers' loaders unmodified and
compare with references written here from the take (`take.sensor(name).events`, the simulator's ground-truth
board corners). 4DGaussians and Dynamic3DGaussians import CUDA extensions: the checks stub them
in the scratch venv only (consumer_checks/cuda_stubs.py) and say so in their output. For
nerfstudio, `ns-train nerfacto --max-num-iterations 3` runs on the CPU up to where it needs the
internet or a GPU. One PASS/FAIL line per consumer; exit code 1 if any failed.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from firmware_sim.board_scene import BoardScene
from firmware_sim.testing.board import true_mid_exposures
from firmware_sim.world import get_world
from rigd.app.capture import run_capture
from rigd.app.config import RigConfig
from rigd.app.testing.board import board_rig, capture_board_take
from rigd.products.export import ExportOptions, run_export
from rigd.take.reader import open_take

log = logging.getLogger(__name__)

RES = (480, 270)
WORLD = "consumers"
CHECKS = Path(__file__).resolve().parent / "consumer_checks"
TORCH_WHEEL = os.environ.get("RIGD_TORCH_WHEEL", "torch")
"""What pip installs for torch (a CPU wheel file where the registry's CUDA build is unwanted)."""


@dataclass(frozen=True)
class Repo:
    url: str
    commit: str


REPOS = {
    "dsec": Repo("https://github.com/uzh-rpg/DSEC", "af90ef112c175ddcb29d7bfefde517a877c18172"),
    "dynamic3dgaussians": Repo(
        "https://github.com/JonathonLuiten/Dynamic3DGaussians", "7dbbd4dec404308524ff402756bdb8143a2589b0"
    ),
    "4dgaussians": Repo("https://github.com/hustvl/4DGaussians", "843d5ac636c37e4b611242287754f3d4ed150144"),
}

#: pip requirements of each scratch venv, installed in order (torch first where needed).
VENVS: dict[str, list[list[str]]] = {
    "dsec": [["numpy>=2", "h5py", "numba"]],
    "tonic": [["numpy>=2", "h5py", "tonic"]],
    "dynamic3dgaussians": [[TORCH_WHEEL], ["open3d", "pillow", "tqdm", "numpy<2"]],
    "4dgaussians": [
        [TORCH_WHEEL],
        [
            "torchvision",
            "open3d",
            "pillow",
            "tqdm",
            "plyfile",
            "scipy",
            "matplotlib",
            "opencv-python-headless",
            "numpy<2",
        ],
    ],
    "nerfstudio": [[TORCH_WHEEL], ["nerfstudio==1.1.5"]],
}


def run(
    cmd: list[str], cwd: Path | None = None, env: dict[str, str] | None = None, timeout: float = 3600
) -> str:
    """Run a command; its output (stdout and stderr); a RuntimeError with the tail when it fails."""
    p = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout, check=False)
    out = p.stdout + p.stderr
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[:4])} ... exited {p.returncode}:\n{out[-3000:]}")
    return out


def venv(work: Path, name: str) -> Path:
    """The venv's python, made and filled once (a marker file says it is complete)."""
    root = work / "venvs" / name
    py = root / "bin" / "python"
    if not (root / ".rigd-complete").exists():
        if not py.exists():
            run([sys.executable, "-m", "venv", str(root)])
        keep: list[str] = []
        for reqs in VENVS[name]:
            run([str(py), "-m", "pip", "install", "-q", *reqs, *keep])
            if reqs == [TORCH_WHEEL]:  # later installs keep this torch (no CUDA build from the registry)
                version = run([str(py), "-c", "import torch; print(torch.__version__)"]).strip()
                keep = [f"torch=={version.split('+')[0]}"]
        (root / ".rigd-complete").write_text(time.strftime("%Y-%m-%d %H:%M:%S\n"))
    return py


def source_of(repo: Repo) -> str:
    """Where to fetch a repository: GitHub, or a local mirror of it (`RIGD_GIT_MIRROR`: a directory
    holding `<owner>+<name>/repo` git directories) where GitHub cannot be reached."""
    mirror = os.environ.get("RIGD_GIT_MIRROR")
    if mirror:
        owner, name = repo.url.rstrip("/").split("/")[-2:]
        local = Path(mirror) / f"{owner}+{name}" / "repo"
        if local.is_dir():
            return str(local)
    return repo.url


def checkout(work: Path, name: str) -> Path:
    """The consumer's source at its pinned commit (fetched once). From a local mirror whose
    largest files are absent, the commit's tree is written file by file and what is missing is
    listed in `.rigd-missing` (the checks fail if they need it)."""
    repo = REPOS[name]
    dest = work / "src" / name
    stamp = dest / ".rigd-commit"
    if not stamp.exists():
        source = source_of(repo)
        dest.mkdir(parents=True, exist_ok=True)
        if source == repo.url:
            run(["git", "init", "-q"], cwd=dest)
            run(["git", "fetch", "-q", "--depth", "1", source, repo.commit], cwd=dest)
            run(["git", "checkout", "-q", "FETCH_HEAD"], cwd=dest)
            head = run(["git", "rev-parse", "HEAD"], cwd=dest).strip()
            if head != repo.commit:
                raise RuntimeError(f"{dest}: at {head}, expected the pinned {repo.commit}")
        else:
            missing = _write_tree(Path(source), repo.commit, dest)
            (dest / ".rigd-missing").write_text("".join(f"{m}\n" for m in missing))
        stamp.write_text(repo.commit + "\n")
    if stamp.read_text().strip() != repo.commit:
        raise RuntimeError(f"{dest}: holds {stamp.read_text().strip()}, expected the pinned {repo.commit}")
    return dest


def _write_tree(git_dir: Path, commit: str, dest: Path) -> list[str]:
    """Every blob of the commit's tree under dest; the paths whose blob the mirror lacks."""
    listing = run(["git", "--git-dir", str(git_dir), "ls-tree", "-r", "-z", commit])
    missing = []
    for entry in filter(None, listing.split("\0")):
        meta, path = entry.split("\t", 1)
        _, kind, sha = meta.split()
        if kind != "blob":
            continue
        p = subprocess.run(
            ["git", "--git-dir", str(git_dir), "cat-file", "blob", sha], capture_output=True, check=False
        )
        if p.returncode != 0:
            missing.append(path)
            continue
        out = dest / path
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(p.stdout)
    return missing


# --- takes, exports and references ---------------------------------------------------------


def make_takes(work: Path, seconds: float) -> tuple[Path, Path]:
    """(board take, the same rig with the box clock 5000 s after power-on: rig us > 2^32)."""
    take = capture_board_take(work / "take", seconds, RES, world=WORLD, clock="virtual").path
    data = board_rig(WORLD + "-late", RES, clock="virtual").model_dump()
    data["trigger"]["spec"] += "&offset_us=5000000000"
    late = run_capture(RigConfig.model_validate(data), work / "late", min(seconds, 1.0)).path
    return take, late


def export(take: Path, fmt: str, out: Path) -> Path:
    out.parent.mkdir(parents=True, exist_ok=True)
    run_export(ExportOptions(take=take, format=fmt, out=out, force=out.exists()))  # type: ignore[arg-type]
    return out


def dsec_reference(take: Path, export_dir: Path, n_windows: int = 22) -> Path:
    """Windows between consecutive frame times (the export's us) and `take.sensor(name).events` in each."""
    stamps = np.array(
        [int(s) for s in (export_dir / "images" / "cam0" / "timestamps.txt").read_text().split()]
    )
    origin = int(json.loads((export_dir / "split.json").read_text())["rig_time_origin_us"])
    windows = np.stack([stamps[:-1], stamps[1:]], axis=1)[:n_windows]
    parts: dict[str, list[np.ndarray]] = {"x": [], "y": [], "t": [], "p": []}
    with open_take(take) as tk:
        sensors = tk.event_sensors
        bounds = np.zeros((len(sensors), len(windows), 2), np.int64)
        n = 0
        for s, sensor in enumerate(sensors):
            for w, (a, b) in enumerate(windows):
                ev = tk.sensor(sensor).events(origin + int(a), origin + int(b))
                bounds[s, w] = n, n + len(ev)
                n += len(ev)
                parts["x"].append(ev.x)
                parts["y"].append(ev.y)
                parts["t"].append(ev.t.astype(np.int64))
                parts["p"].append((ev.p > 0).astype(np.uint8))
    dest = export_dir.parent / f"{export_dir.name}-reference.npz"
    np.savez(
        dest,
        sensors=np.array(sensors),
        origin=origin,
        windows=windows,
        bounds=bounds,
        **{k: np.concatenate(v) for k, v in parts.items()},
    )
    return dest


def board_views(take: Path, export_dir: Path) -> Path:
    """views.json of a PanopticSports export: per image with the whole board in view, the
    ground-truth corners in the export's world and the corners cv2 finds (pixel centres at
    integers, as the rasterizer draws)."""
    scene = get_world(WORLD).resource("scene", BoardScene)
    assert isinstance(scene, BoardScene)
    truth = true_mid_exposures(take, WORLD)
    result = json.loads((export_dir / "export.json").read_text())
    M = np.asarray(result["rig_to_world"], np.float64)
    with open_take(take) as tk:
        board = tk.board_pose
    assert board is not None, "the sim take stores its board plane"
    pattern = (scene.cols, scene.rows)
    views = []
    for split in ("train", "test"):
        meta = json.loads((export_dir / f"{split}_meta.json").read_text())
        for fns, names, times in zip(meta["fn"], meta["cam_name"], meta["t_us"], strict=True):
            for fn, cam, t_us in zip(fns, names, times, strict=True):
                gray = cv2.imread(str(export_dir / "ims" / fn), cv2.IMREAD_GRAYSCALE)
                ok, corners = cv2.findChessboardCorners(gray, pattern)
                if not ok:
                    continue
                crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
                found = cv2.cornerSubPix(gray, corners, (3, 3), (-1, -1), crit).reshape(-1, 2)
                R_b, t_b = scene.board_pose(truth[cam][int(t_us)])
                X_sim = scene.board_points() @ R_b.T + t_b
                X_rig = X_sim @ board[0].T + board[1]
                X = X_rig @ M[:3, :3].T + M[:3, 3]
                if _closer_reversed(found, X, fn, meta):
                    found = found[::-1]
                views.append({"fn": fn, "X": X.tolist(), "uv": found.tolist()})
    dest = export_dir.parent / f"{export_dir.name}-views.json"
    dest.write_text(json.dumps(views))
    return dest


def _closer_reversed(found: np.ndarray, X: np.ndarray, fn: str, meta: dict[str, object]) -> bool:
    """The detector may list the corners in reverse order: pick the order nearer the projection
    (projected here with the meta's own K and w2c, OpenCV pixels, to order them only)."""
    for row_fn, row_k, row_w2c in zip(meta["fn"], meta["k"], meta["w2c"], strict=True):  # type: ignore[call-overload]
        if fn in row_fn:
            c = row_fn.index(fn)
            K, w2c = np.asarray(row_k[c]), np.asarray(row_w2c[c])
            x = (X @ w2c[:3, :3].T + w2c[:3, 3]) @ K.T
            uv = x[:, :2] / x[:, 2:3]
            return bool(
                np.linalg.norm(found[::-1] - uv, axis=1).mean() < np.linalg.norm(found - uv, axis=1).mean()
            )
    raise KeyError(fn)


# --- the consumers ------------------------------------------------------------------------


def check_env(work: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(CHECKS)
    env["CHECK_WORK"] = str(work)
    env.pop("PIP_CONSTRAINT", None)
    return env


def consumer_dsec(work: Path, ex: dict[str, Path]) -> str:
    py, src = venv(work, "dsec"), checkout(work, "dsec")
    args = [str(ex["dsec"]), str(ex["dsec-ref"]), str(ex["dsec-late"]), str(ex["dsec-late-ref"])]
    return run([str(py), str(CHECKS / "dsec_check.py"), str(src), *args], env=check_env(work))


def consumer_tonic(work: Path, ex: dict[str, Path]) -> str:
    py = venv(work, "tonic")
    return run(
        [str(py), str(CHECKS / "tonic_check.py"), str(ex["dsec"]), str(ex["dsec-ref"])], env=check_env(work)
    )


def consumer_dynamic3dgaussians(work: Path, ex: dict[str, Path]) -> str:
    py, src = venv(work, "dynamic3dgaussians"), checkout(work, "dynamic3dgaussians")
    cmd = [
        str(py),
        str(CHECKS / "d3dgs_check.py"),
        str(src),
        str(ex["dynamic3dgs"]),
        str(ex["dynamic3dgs-views"]),
    ]
    return run(cmd, env=check_env(work))


def consumer_4dgaussians(work: Path, ex: dict[str, Path]) -> str:
    py, src = venv(work, "4dgaussians"), checkout(work, "4dgaussians")
    cmd = [
        str(py),
        str(CHECKS / "fourdg_check.py"),
        str(src),
        str(ex["4dgaussians"]),
        str(ex["4dgaussians-views"]),
    ]
    return run(cmd, cwd=src, env=check_env(work))


def consumer_nerfstudio(work: Path, ex: dict[str, Path]) -> str:
    py = venv(work, "nerfstudio")
    env = check_env(work)
    out = run([str(py), str(CHECKS / "nerfstudio_check.py"), str(ex["nerfstudio"])], env=env)
    ns_train = py.parent / "ns-train"
    env = {**env, "PYTHONPATH": str(CHECKS / "ns_site")}  # its sitecustomize stubs a CUDA-only torchvision
    cmd = [
        str(ns_train), "nerfacto", "--data", str(ex["nerfstudio"]), "--max-num-iterations", "3",
        "--machine.device-type", "cpu", "--vis", "tensorboard", "--output-dir", str(work / "ns-outputs"),
        "--viewer.quit-on-train-completion", "True", "nerfstudio-data",
    ]  # fmt: skip
    p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=3600, check=False)
    text = p.stdout + p.stderr
    tail = "\n".join("    " + ln for ln in text.strip().splitlines()[-6:])
    if p.returncode == 0:
        return out + f"  ns-train nerfacto --max-num-iterations 3 (CPU): finished\n{tail}\n"
    data_ready = "overriding val_indices" in text and "Saving checkpoints" in text
    if data_ready and "stubbed here only: torchvision" in text:
        return (
            out + f"  ns-train nerfacto: data set up (splits, images), then stopped in the model's setup, "
            f"which needs torchvision (stubbed: only its CUDA build installs here):\n{tail}\n"
        )
    if any(k in text for k in ("CUDA", "cuda", "urlopen", "ConnectionError", "Name or service not known")):
        return (
            out + f"  ns-train nerfacto: data set up, then stopped needing a GPU or the internet:\n{tail}\n"
        )
    raise RuntimeError(f"ns-train failed before needing a GPU or the internet:\n{text[-3000:]}")


def prepare(work: Path, seconds: float) -> dict[str, Path]:
    """The takes, their exports and the references the checks compare with."""
    take, late = make_takes(work, seconds)
    ex: dict[str, Path] = {"take": take, "late": late}
    for fmt in ("nerfstudio", "4dgaussians", "dynamic3dgs", "dsec"):
        ex[fmt] = export(take, fmt, work / "exports" / fmt)
    ex["dsec-late"] = export(late, "dsec", work / "exports" / "dsec-late")
    ex["dsec-ref"] = dsec_reference(take, ex["dsec"])
    ex["dsec-late-ref"] = dsec_reference(late, ex["dsec-late"])
    for fmt in ("4dgaussians", "dynamic3dgs"):
        ex[f"{fmt}-views"] = board_views(take, ex[fmt])
    return ex


CONSUMERS = {
    "dsec": consumer_dsec,
    "tonic": consumer_tonic,
    "dynamic3dgaussians": consumer_dynamic3dgaussians,
    "4dgaussians": consumer_4dgaussians,
    "nerfstudio": consumer_nerfstudio,
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/rigd-consumers"), help="scratch directory")
    ap.add_argument("--only", default=",".join(CONSUMERS), help="comma-separated consumers to check")
    ap.add_argument("--seconds", type=float, default=2.0, help="length of the board take")
    ap.add_argument(
        "--reuse", action="store_true", help="reuse the take and exports of an earlier run in --work"
    )
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    work: Path = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    names = [n for n in args.only.split(",") if n]
    unknown = set(names) - set(CONSUMERS)
    if unknown:
        ap.error(f"--only: unknown {sorted(unknown)} (known: {', '.join(CONSUMERS)})")
    t0 = time.perf_counter()
    prepared = work / "prepared.json"
    if args.reuse and prepared.exists():
        ex = {k: Path(v) for k, v in json.loads(prepared.read_text()).items()}
        print(f"exports of {ex['take'].name} reused from {work / 'exports'}")
    else:
        ex = prepare(work, args.seconds)
        prepared.write_text(json.dumps({k: str(v) for k, v in ex.items()}))
        print(
            f"take {ex['take'].name} ({args.seconds:g} s, {RES[0]}x{RES[1]}), exports in {work / 'exports'} "
            f"({time.perf_counter() - t0:.0f} s)"
        )
    failed = []
    for name in names:
        where = f" @ {REPOS[name].commit[:12]}" if name in REPOS else ""
        try:
            out = CONSUMERS[name](work, ex)
            print(f"PASS {name}{where}\n{out.rstrip()}")
        except Exception as exc:  # noqa: BLE001  (every consumer is reported, then the exit code says)
            failed.append(name)
            print(f"FAIL {name}{where}: {exc}")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
