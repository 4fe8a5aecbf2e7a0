"""The expert's reference: mrcal-calibrate-cameras fed the same detected ChArUco corners.

mrcal 2.2 (Debian's, run by /usr/bin/python3, never the venv) reads a corners file and solves with its own
seeding, regularization, board-warp fit and outlier rejection (its default). corners.vnl is a vnlog
`# filename x y level`: per image one row per board point in mrcal's (H, W) row-major grid, which is
ChArUco's id order (id = row * W + col, W = squares_x - 1, H = squares_y - 1); a point not detected is
`filename - - -`, a detected one has level 0 (weight 1). The images need not exist: the glob matches names.

Lens models: pinhole -> LENSMODEL_OPENCV5, rational -> LENSMODEL_OPENCV8, fisheye ->
LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=20_Ny=12_fov_x_deg=1.1 x the lens's field of view (mrcal 2.2
has no Kannala-Brandt; splined is its recommendation for wide lenses; knots: see SPLINED). --focal is the
stereographic focal length of a rough field of view, (W / 2) / (2 tan(fov / 4)): the tool seeds every model
from a LENSMODEL_STEREOGRAPHIC solve (run through _MENDED, see PARTIAL VIEWS). Scoring is calibcoach's
`projection_difference` (truth's grid unprojected, one rotation fitted) with mrcal.project doing the projecting.

    .venv/bin/python bench/mrcal_reference.py [--seeds 1 2] [--frames 100]   # -> bench/results/mrcal_reference.md
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from calibcoach.app.solve.uncertainty import DEFAULT_DISTANCE_M, covered_region_mask, image_grid
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector, Detection
from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.sim import LENSES, SimulatedCamera, handheld_trajectory

MRCAL_PYTHON = "/usr/bin/python3"
ROUGH_FOV_DEG = {"pinhole": 70.0, "rational": 115.0, "fisheye": 150.0}  # a datasheet's field of view
# mrcal's examples use Nx=30 Ny=20 for dense captures of a large board; on ~60 partial views of this A4
# board that density is data-starved (fisheye150 seeds 1, 2: 0.99 and 0.57 px against the truth), 20x12
# gives 0.35 and 0.16 px, 12x7 0.27 and 0.17 px. 20x12 (square knots for 16:9) is the default.
SPLINED = "LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=20_Ny=12_fov_x_deg={fov:.0f}"
MIN_CORNERS = 6


@dataclass
class MrcalSolution:
    """mrcal-calibrate-cameras' answer, or why there is none (`error`)."""

    lensmodel: str
    command: list[str]
    cameramodel: Path | None = None
    rms_px: float = float("nan")  # mrcal's final RMS reprojection error (outliers excluded)
    outliers: int = 0  # detected corners mrcal rejected
    points: int = 0  # detected corners given to mrcal
    seconds: float = 0.0
    error: str = ""
    log: str = field(default="", repr=False)

    command_line = property(lambda self: shlex.join(self.command))


def clean_env() -> dict[str, str]:
    """The environment without the venv's Python, one BLAS thread (the machine is shared)."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    return {**env, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}


def mrcal_missing() -> str:
    """Why mrcal cannot be run here ("" when it can)."""
    if not Path(MRCAL_PYTHON).is_file():
        return f"{MRCAL_PYTHON} is absent, so Debian's python3-mrcal cannot be run"
    if subprocess.run([MRCAL_PYTHON, "-c", "import mrcal"], capture_output=True, env=clean_env(), check=False).returncode:
        return f"{MRCAL_PYTHON} has no mrcal module: apt-get install -y python3-mrcal"
    if _tool() is None:
        return "mrcal-calibrate-cameras is not installed: apt-get install -y mrcal"
    return ""


def _tool() -> str | None:  # the Debian package's, whatever the venv puts first on PATH
    return shutil.which("mrcal-calibrate-cameras", path="/usr/bin:/usr/local/bin:" + os.environ.get("PATH", ""))


def lensmodel_for(lens: str, fov_deg: float) -> str:
    models = {"pinhole": "LENSMODEL_OPENCV5", "rational": "LENSMODEL_OPENCV8", "fisheye": SPLINED.format(fov=1.1 * fov_deg)}
    if lens not in models:
        raise ValueError(f"lens must be pinhole, rational or fisheye, got {lens!r}")
    return models[lens]


def stereographic_focal(width: int, fov_deg: float) -> float:
    return (width / 2) / (2 * np.tan(np.radians(fov_deg) / 4))


def write_corners(path: Path, views: Sequence[Detection], names: Sequence[str], spec: BoardSpec) -> None:
    """mrcal's corners file: every board point of every view, `- - -` where it was not detected."""
    n = spec.corner_count
    lines = ["# filename x y level"]
    for name, view in zip(names, views, strict=True):
        xy = np.full((n, 2), np.nan)
        xy[np.asarray(view.ids, int)] = np.asarray(view.corners_px, np.float64)
        lines += [f"{name} - - -" if np.isnan(x) else f"{name} {x:.6f} {y:.6f} 0" for x, y in xy]
    path.write_text("\n".join(lines) + "\n", encoding="ascii")


def solve_with_mrcal(views: Sequence[Detection], spec: BoardSpec, image_size: tuple[int, int], lens: str,
                     workdir: Path, *, names: Sequence[str] | None = None, fov_deg: float | None = None,
                     timeout_s: float = 1800.0) -> MrcalSolution:
    """Calibrate `views` (>= 6 corners each are kept) with mrcal-calibrate-cameras; never raises on mrcal's failure.

    `names` label the views in the corners file (default frame00000.png ...); `fov_deg` is the rough
    horizontal field of view that seeds the focal length (default: the lens kind's, ROUGH_FOV_DEG).
    """
    workdir, fov = Path(workdir).resolve(), ROUGH_FOV_DEG[lens] if fov_deg is None else float(fov_deg)
    lensmodel = lensmodel_for(lens, fov)
    names = [f"frame{i:05d}.png" for i in range(len(views))] if names is None else [re.sub(r"\W", "_", str(n)) + ".png" for n in names]
    kept = [(nm, v) for nm, v in zip(names, views, strict=True) if v.corner_count >= MIN_CORNERS]
    (corners, outdir), (w, h) = (workdir / "corners.vnl", workdir / "out"), image_size
    command = [_tool() or "mrcal-calibrate-cameras", "--corners-cache", str(corners), "--lensmodel", lensmodel,
               "--focal", f"{stereographic_focal(w, fov):.1f}", "--imagersize", str(w), str(h),
               "--object-spacing", f"{spec.square_mm / 1000:.6g}", "--object-width-n", str(spec.squares_x - 1),
               "--object-height-n", str(spec.squares_y - 1), "--outdir", str(outdir), "*.png"]
    solution = MrcalSolution(lensmodel, command)
    if len(kept) < 3:
        return replace(solution, error=f"only {len(kept)} views with >= {MIN_CORNERS} corners")
    outdir.mkdir(parents=True, exist_ok=True)
    write_corners(corners, [v for _, v in kept], [nm for nm, _ in kept], spec)
    start = time.perf_counter()
    try:
        run = subprocess.run([MRCAL_PYTHON, "-c", _MENDED, *command], cwd=workdir,
                             capture_output=True, text=True, env=clean_env(), check=False, timeout=timeout_s)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return replace(solution, error=f"{type(exc).__name__}: {exc}"[:200])
    solution.seconds, solution.log = time.perf_counter() - start, run.stdout + run.stderr
    if run.returncode or not (model := outdir / "camera-0.cameramodel").is_file():
        last = [ln for ln in run.stderr.strip().splitlines() if ln.strip()] or [f"exit status {run.returncode}"]
        return replace(solution, error=last[-1][:200])
    solution.cameramodel = model
    rms = re.findall(r"## RMS error: (\S+)", run.stderr)
    solution.rms_px = float(rms[-1]) if rms else float("nan")
    outliers = re.search(r"Noutliers: (\d+) out of (\d+)", run.stdout)
    if outliers:  # mrcal counts the points marked missing (`- - -`) among its outliers
        observed = sum(v.corner_count for _, v in kept)
        solution.points, solution.outliers = observed, int(outliers[1]) - (int(outliers[2]) - observed)
    return solution


# PARTIAL VIEWS. mrcal 2.2 reads `- - -` as a missing point (x = y = -1, weight -1) and its solver skips it,
# but its seeding (estimate_monocular_calobject_poses_Rt_tocam, in seed_stereographic) drops NaN points only,
# so each partial view's missing corners went into solvePnP at pixel (-1, -1): wrong board poses, the
# stereographic core fit walked cx to ~ -2000 px and the solve diverged (RMS 85 px on the demo recording) or
# stopped on "Cannot compute the uncertainty" (mrgingham, the tool's detector, reports whole boards only).
# _MENDED runs the installed tool unchanged but for that seeding seeing missing points as NaN.
_MENDED = r"""
import sys
import numpy as np
import mrcal
tool = sys.argv[1]
seed_poses = mrcal.estimate_monocular_calobject_poses_Rt_tocam

def poses_from_detected_points(indices_frame_camera, observations, *args, **kwargs):
    observations = np.array(observations, dtype=float)
    observations[observations[..., 2] < 0] = np.nan  # 2.2 filters NaN only, so (-1, -1) went into solvePnP
    return seed_poses(indices_frame_camera, observations, *args, **kwargs)

mrcal.estimate_monocular_calobject_poses_Rt_tocam = poses_from_detected_points
sys.argv = sys.argv[1:]
exec(compile(open(tool).read(), tool, "exec"), {"__name__": "__main__", "__file__": tool})
"""


# --- scoring against the truth, mrcal projecting ------------------------------------------------------

_SCORE = r"""
import json, sys
import numpy as np
import mrcal
data = np.load(sys.argv[1])
lensmodel, intrinsics = mrcal.cameramodel(sys.argv[2]).intrinsics()
q, points, keep = data["q"], data["points"], data["keep"]

def projectable(p):  # calibcoach's _projectable: in front, finite, and back to the same ray within 1e-6 rad
    ok, n = np.zeros(len(p), bool), np.linalg.norm(p, axis=1)
    front = p[:, 2] > 1e-9 * n
    if not front.any():
        return ok
    px = mrcal.project(np.ascontiguousarray(p[front]), lensmodel, intrinsics)
    finite = np.all(np.isfinite(px), axis=1)
    back, unit = np.zeros((len(px), 3)), p[front] / n[front, None]
    if finite.any():
        back[finite] = mrcal.unproject(np.ascontiguousarray(px[finite]), lensmodel, intrinsics, normalize=True)
    angle = np.linalg.norm(np.cross(back, unit), axis=1)
    ok[np.nonzero(front)[0]] = finite & (angle < 1e-6) & (np.sum(back * unit, axis=1) > 0)
    return ok

ok, r, rotated = projectable(points) & keep, np.zeros(3), points
if ok.sum() >= 2:
    for _ in range(10):  # Gauss-Newton on the Rodrigues vector, as compare.py does with OpenCV's Jacobian
        p, dp_dr, _ = mrcal.rotate_point_r(r, points[ok], get_gradients=True)
        proj, dq_dp, _ = mrcal.project(p, lensmodel, intrinsics, get_gradients=True)
        J = np.einsum("nij,njk->nik", dq_dp, dp_dr).reshape(-1, 3)
        step = np.linalg.lstsq(J, -(proj - q[ok]).reshape(-1), rcond=None)[0]
        r = r + step
        if np.linalg.norm(step) < 1e-12:
            break
    rotated = mrcal.rotate_point_r(r, points)
    ok &= projectable(rotated)
diff = np.linalg.norm(mrcal.project(np.ascontiguousarray(rotated[ok]), lensmodel, intrinsics) - q[ok], axis=1)
print(json.dumps({"rms_px": float(np.sqrt(np.mean(diff ** 2))) if diff.size else float("nan"), "rotation": r.tolist()}))
"""


def mrcal_error_vs_truth(truth: CameraModel, cameramodel: Path, mask: np.ndarray | None = None,
                         grid: tuple[int, int] = (32, 18)) -> float:
    """RMS px between the truth and a .cameramodel over `mask`'s grid points, after the best rotation.

    The same definition as `projection_difference(truth, estimate, grid=grid, mask=mask).rms_px`.
    """
    gx, gy = image_grid(truth.image_size, grid)
    q = np.stack([c.reshape(-1) for c in np.meshgrid(gx, gy)], axis=1)
    keep = np.ones(q.shape[0], bool) if mask is None else np.asarray(mask, bool).reshape(-1)
    with tempfile.TemporaryDirectory() as tmp:
        np.savez(arrays := Path(tmp) / "grid.npz", q=q, points=truth.unproject(q) * DEFAULT_DISTANCE_M, keep=keep)
        run = subprocess.run([MRCAL_PYTHON, "-c", _SCORE, str(arrays), str(cameramodel)], capture_output=True,
                             text=True, env=clean_env(), check=False, timeout=300)
    if run.returncode:
        raise RuntimeError(f"mrcal scoring failed: {run.stderr.strip()[-300:]}")
    return float(json.loads(run.stdout)["rms_px"])


# --- the bench: rendered captures, mrcal beside the plain recipe ----------------------------------------

LENS_KIND = {"webcam720": "pinhole", "wide720": "rational", "fisheye150": "fisheye"}


def rendered_views(lens_name: str, seed: int, *, frames: int, fps: float = 5.0) -> list[tuple[int, Detection]]:
    """Detections of a careful handheld capture (cached in bench/cache/, git-ignored)."""
    cache = Path(__file__).resolve().parent / "cache" / f"mrcal_{lens_name}_careful_{frames}f_seed{seed}.pickle"
    if cache.is_file():
        return pickle.loads(cache.read_bytes())
    camera, spec, seconds = LENSES[lens_name], BoardSpec(), frames / fps
    trajectory = handheld_trajectory(camera, spec, "careful", seconds=seconds, seed=seed)
    source = SimulatedCamera(camera, spec, trajectory.sample(seconds=seconds, fps=fps), seed=seed, lens_name=lens_name,
                             trajectory=trajectory)
    detector = CharucoBoardDetector(spec)
    views = [(frame.index, detector.detect(frame.grey())) for frame in source]
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_bytes(pickle.dumps(views))
    return views


def main() -> int:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from accuracy import crash_note, score, solve_plain  # bench/accuracy.py, beside this script

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--lenses", nargs="+", default=list(LENS_KIND))
    args = parser.parse_args()
    if why := mrcal_missing():
        return print(f"mrcal unavailable: {why}") or 1
    commands = []
    rows = ["| lens | seed | views | plain calibrateCamera, px | mrcal, px | mrcal model | mrcal RMS, px | outliers | mrcal s |",
            "|---|---|---|---|---|---|---|---|---|"]
    for lens_name in args.lenses:
        truth = LENSES[lens_name]
        for seed in args.seeds:
            views = [d for _, d in rendered_views(lens_name, seed, frames=args.frames) if d.corner_count >= MIN_CORNERS]
            mask = covered_region_mask(truth.image_size, [d.corners_px for d in views], (32, 18))
            try:
                plain = f"{score(truth, solve_plain(views, truth), [d.corners_px for d in views]):.4f}"
            except Exception as exc:  # cv2.error: the plain recipe can crash; the row says so
                plain = crash_note(exc)
            with tempfile.TemporaryDirectory() as tmp:
                sol = solve_with_mrcal(views, BoardSpec(), truth.image_size, LENS_KIND[lens_name], Path(tmp))
                commands.append(f"- {lens_name}: `" + sol.command_line.replace(tmp, "WORKDIR") + "`")
                ours = f"mrcal failed: {sol.error}" if sol.error else f"{mrcal_error_vs_truth(truth, sol.cameramodel, mask):.4f}"
            short = sol.lensmodel.replace("LENSMODEL_", "")
            rows.append(f"| {lens_name} | {seed} | {len(views)} | {plain} | {ours} | {short} | {sol.rms_px:.3f} | "
                        f"{sol.outliers}/{sol.points} | {sol.seconds:.0f} |")
            print(rows[-1], flush=True)
    text = "\n".join([f"# mrcal-calibrate-cameras beside the plain recipe ({args.frames} careful frames, >= {MIN_CORNERS} corners)",
                      "", "Error against the lens truth over the covered image (px, 32x18 grid, rotation fitted).", "",
                      *rows, "", "Commands (run through _MENDED, bench/mrcal_reference.py):", *dict.fromkeys(commands), ""])
    (Path(__file__).resolve().parent / "results" / "mrcal_reference.md").write_text(text, encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
