"""Accuracy across renders: calibcoach against the plain recipe, a ROS-style selector and mrcal.

Every cell of bench/renders.py (lens, hand from steady to shaky, exposure drawn per render, PNG
folder or MJPG video, normal or low light) is rendered with 5 seeds that no tuning has used, and
each capture is calibrated five ways from the same footage:

  plain      the method's recipe: every 30th frame (1 per second at 30 fps) with >= 6 corners into
             calibrateCamera, with the model the recipe names for the lens's field of view;
  ROS-style  a frame is kept when its (x, y, size, skew) differs from every kept one by 0.2 (L1);
  mrcal      `mrcal-calibrate-cameras` on the detected corners of every still frame (smear in the
             exposure under 1.5 px by the truth, the selector's limit), the expert's reference (when python3-mrcal is there);
  calibcoach `run_replay` + `finish` with the defaults, and with `every_frame`.

Scored by the projection error against the lens truth over the region the capture's boards
covered (every frame with >= 6 corners; the one rotation an extrinsic absorbs is fitted), reported
as median and worst over the seeds, with how often calibcoach accepted. For PNG folders the replay
time is compared with the plain loop (imread + detectBoard on every frame + one calibrateCamera over
every usable frame), both measured in this process, one after the other.

    .venv/bin/python bench/heldout.py [--cells careful720_png ...] [--seeds 101 102 ...] [--no-mrcal]
    .venv/bin/python bench/heldout.py --cached --calibcoach-only --out NAME   # the scan against --every-frame, every cached render

Writes bench/results/heldout.md and bench/results/heldout.json (every run's numbers).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))

from accuracy import crash_note, score, select_ros, solve_plain  # noqa: E402  (bench/accuracy.py)
from renders import CACHE, CELLS, SEEDS, cached_renders, capture_path, render  # noqa: E402

from calibcoach.app.replay import run_replay  # noqa: E402
from calibcoach.coverage.board import BoardSpec  # noqa: E402
from calibcoach.coverage.detector import CharucoBoardDetector, Detection  # noqa: E402
from calibcoach.drivers.lens import CameraModel  # noqa: E402
from calibcoach.drivers.recording import read_truth  # noqa: E402
from calibcoach.drivers.replay import open_source  # noqa: E402
from calibcoach.drivers.sim import effective_exposure_s  # noqa: E402

PLAIN_EVERY = 30  # frames: the recipe's "one frame a second" at 30 fps
STILL_SMEAR_PX = 1.5  # a frame whose corners moved less than this during the exposure is still (mrcal's input): the selector's own smear limit
TRUSTED = ("excellent", "good", "acceptable")
MRCAL_FRAMES = 150


def recipe_model(camera: CameraModel) -> str:
    """The model the method's recipe names for the lens: by its horizontal field of view."""
    hfov = camera.field_of_view_deg()[0]
    return "fisheye" if hfov >= 120 else "rational" if hfov > 90 else "pinhole"


@dataclass
class Run:
    cell: str
    seed: int
    method: str
    error_px: float = float("nan")
    frames: int = 0
    outcome: str = ""
    seconds: float = float("nan")
    extra: dict = field(default_factory=dict)


def detect_all(path: Path) -> tuple[dict[int, Detection], float]:
    """Every frame's detection by index, and the plain loop's detection time (imread included)."""
    detector = CharucoBoardDetector(BoardSpec())
    start = time.perf_counter()
    found = {frame.index: detector.detect(frame.grey()) for frame in open_source(path)}
    return found, time.perf_counter() - start


def cached_capture(name: str):
    """(path, truth, yardstick) of the cached render `name` (e.g. "dim720_mjpg_s101"): the capture
    calibcoach reads, its lens truth, and the corners of every frame with >= 6 (the covered region)."""
    cell, seed = name.rsplit("_s", 1)
    path = capture_path(cell, int(seed))
    found, _seconds = detect_all(path)
    return path, read_truth(CACHE / name), [d.corners_px for _i, d in sorted(found.items()) if d.corner_count >= 6]


def render_exposure_s(name: str) -> float:
    """The exposure cached render `name` was made with (the simulator doubles the drawn one in low
    light, up to the frame interval)."""
    cell = CELLS[name.rsplit("_s", 1)[0]]
    return effective_exposure_s(float((CACHE / name / "exposure_s.txt").read_text()), low_light=cell.low_light, fps=cell.fps)


def exposure_smear_px(truth, exposure_s: float, fps: float, spec: BoardSpec) -> dict[int, float]:
    """Largest corner motion within each frame's exposure, from the true poses either side of it."""
    corners = spec.corner_points_m()
    poses = {i: (r, t) for i, r, t in truth.poses}
    projected = {i: truth.camera.project(corners, r, t) for i, (r, t) in poses.items()}
    smear = {}
    for i in poses:
        before, after = projected.get(i - 1, projected[i]), projected.get(i + 1, projected[i])
        steps = 2 if (i - 1 in projected and i + 1 in projected) else 1
        speed = np.linalg.norm(after - before, axis=1).max() / steps  # px per frame
        smear[i] = float(speed * exposure_s * fps)
    return smear


def solve_and_score(name: str, views: list[Detection], truth: CameraModel, model: str, yardstick) -> Run:
    run = Run("", 0, name, frames=len(views))
    try:
        estimate = solve_plain(views, CameraModel(model, truth.camera_matrix, np.zeros(8), truth.image_size))
        run.error_px = score_on(truth, estimate, yardstick)
        run.outcome = "accepted"
    except cv2.error as exc:
        run.outcome = crash_note(exc)
    return run


def score_on(truth: CameraModel, estimate: CameraModel, yardstick) -> float:
    return score(truth, estimate, yardstick)


def calibcoach_run(path: Path, truth: CameraModel, yardstick, *, every_frame: bool) -> Run:
    name = "calibcoach --every-frame" if every_frame else "calibcoach"
    run = Run("", 0, name)
    source = open_source(path)
    start = time.perf_counter()
    session, stats = run_replay(source, BoardSpec(), every_frame=every_frame)
    try:
        result = session.finish()
    except Exception as exc:  # noqa: BLE001 - a bench row says what went wrong
        run.outcome = f"failed: {str(exc)[:80]}"
        run.seconds = time.perf_counter() - start
        return run
    run.seconds = time.perf_counter() - start
    run.error_px = score_on(truth, result.calibration.camera, yardstick)
    run.frames = len(result.calibration.views)
    run.outcome = result.verdict.grade
    run.extra = {"read": stats.frames_read, "tracked": stats.tracked, "model": result.calibration.camera.model,
                 "rms_px": float(result.calibration.rms_px)}
    return run


def plain_loop_seconds(path: Path, detect_s: float, usable: list[Detection], size: tuple[int, int]) -> float:
    """imread + detectBoard on every frame (measured above) + one calibrateCamera over every usable frame."""
    start = time.perf_counter()
    try:
        cv2.calibrateCamera([d.object_points_m.reshape(-1, 1, 3).astype(np.float32) for d in usable],
                            [d.corners_px.reshape(-1, 1, 2).astype(np.float32) for d in usable], size, None, None)
    except cv2.error:
        pass  # a fisheye's frames can defeat the pinhole initialisation: the loop still spent the time
    return detect_s + time.perf_counter() - start


def evaluate(cell_name: str, seed: int, *, use_mrcal: bool, calibcoach_only: bool = False) -> list[Run]:
    """Every method on one render; `calibcoach_only`: the defaults and `--every-frame` alone (the
    held-frame scan against reading every frame, over many renders at ~20 s each)."""
    cell = CELLS[cell_name]
    folder = render(cell_name, seed)
    path = capture_path(cell_name, seed)
    truth = read_truth(folder)
    camera = truth.camera
    spec = BoardSpec()
    dets, detect_s = detect_all(path)
    usable = [d for _i, d in sorted(dets.items()) if d.corner_count >= 6]
    yardstick = [d.corners_px for d in usable]
    # exposure_s.txt holds the exposure drawn for the render; the simulator doubles it in low light, up to 1 / fps
    exposure_s = effective_exposure_s(float((folder / "exposure_s.txt").read_text()), low_light=cell.low_light, fps=cell.fps)
    smear = exposure_smear_px(truth, exposure_s, cell.fps, spec)
    still = [(f"{i:06d}", d) for i, d in sorted(dets.items()) if d.corner_count >= 6 and smear.get(i, 9.0) < STILL_SMEAR_PX]
    runs: list[Run] = []
    if not calibcoach_only:  # the other methods, on the same detections
        model = recipe_model(camera)
        runs += [solve_and_score("plain", [d for i, d in sorted(dets.items()) if i % PLAIN_EVERY == 0 and d.corner_count >= 6],
                                 camera, model, yardstick),
                 solve_and_score("ROS-style", select_ros([d for _i, d in sorted(dets.items())], camera.image_size),
                                 camera, model, yardstick)]
        if use_mrcal:  # at most MRCAL_FRAMES of them, evenly spread (mrcal's solve grows with the views)
            runs.append(mrcal_run(still[:: max(1, -(-len(still) // MRCAL_FRAMES))], spec, camera, model, yardstick, folder))
    for every_frame in (False, True):
        runs.append(calibcoach_run(path, camera, yardstick, every_frame=every_frame))
    if cell.container == "png" and not calibcoach_only:
        plain_s = plain_loop_seconds(path, detect_s, usable, camera.image_size)
        for run in runs:
            if run.method.startswith("calibcoach"):
                run.extra["plain_loop_s"] = plain_s
                run.extra["ratio"] = run.seconds / plain_s
    for run in runs:
        run.cell, run.seed = cell_name, seed
        run.extra["still_frames"] = len(still)
        run.extra["exposure_ms"] = round(exposure_s * 1e3, 1)
    return runs


def mrcal_run(still: list[tuple[str, Detection]], spec: BoardSpec, camera: CameraModel, model: str, yardstick,
              folder: Path) -> Run:
    run = Run("", 0, "mrcal", frames=len(still))
    try:
        from mrcal_reference import mrcal_error_vs_truth, solve_with_mrcal  # bench/mrcal_reference.py
    except ImportError as exc:
        run.outcome = f"not run: {exc}"
        return run
    from calibcoach.app.solve.uncertainty import covered_region_mask

    start = time.perf_counter()
    solution = solve_with_mrcal([d for _n, d in still], spec, camera.image_size, model, folder / "mrcal",
                                names=[n for n, _d in still])
    run.seconds = time.perf_counter() - start
    if getattr(solution, "error", None):
        run.outcome = f"failed: {solution.error[:80]}"
        return run
    mask = covered_region_mask(camera.image_size, yardstick, (32, 18))
    run.error_px = mrcal_error_vs_truth(camera, solution.cameramodel, mask, (32, 18))
    run.outcome = "accepted"
    return run


def summary(runs: list[Run]) -> list[str]:
    lines = ["| cell | method | error vs truth, px: median | worst | frames (median) | outcome | seconds (median) | replay / plain loop (worst) |",
             "|---|---|---|---|---|---|---|---|"]
    cells = sorted({r.cell for r in runs}, key=list(CELLS).index)
    methods = ["plain", "ROS-style", "mrcal", "calibcoach", "calibcoach --every-frame"]
    for cell in cells:
        for method in methods:
            rs = [r for r in runs if r.cell == cell and r.method == method]
            if not rs:
                continue
            errors = np.array([r.error_px for r in rs])
            finite = errors[np.isfinite(errors)]
            med = f"{np.median(finite):.3f}" if finite.size else "-"
            worst = f"{np.max(finite):.3f}" if finite.size == errors.size else "failed" if not finite.size else f"{np.max(finite):.3f} + {errors.size - finite.size} failed"
            if method.startswith("calibcoach"):
                trusted = sum(r.outcome in TRUSTED for r in rs)
                plain = {r.seed: r.error_px for r in runs if r.cell == cell and r.method == "plain"}
                better = sum(bool(np.isfinite(r.error_px)) and not (r.error_px > plain[r.seed]) for r in rs if r.seed in plain)
                outcome = f"{trusted}/{len(rs)} accepted" + (f", <= plain in {better}/{len(rs)}" if plain else "")
            else:
                outcome = ", ".join(sorted({r.outcome for r in rs}))
            secs = np.array([r.seconds for r in rs])
            secs_text = f"{np.nanmedian(secs):.1f}" if np.isfinite(secs).any() else ""
            ratios = [r.extra["ratio"] for r in rs if "ratio" in r.extra]
            ratio = f"{max(ratios):.2f}" if ratios else ""
            lines.append(f"| {cell} | {method} | {med} | {worst} | {int(np.median([r.frames for r in rs]))} | {outcome} | {secs_text} | {ratio} |")
    return lines


BOOTSTRAP_DRAWS = 20_000


def geometric_mean_interval(ratios: np.ndarray, rng: np.random.Generator | None = None) -> str:
    """"g [low, high]": the geometric mean of `ratios` and its 95% bootstrap interval, drawn from
    `rng` (default: a fresh seed-0 generator, so the same ratios always give the same interval)."""
    logs = np.log(ratios)
    rng = np.random.default_rng(0) if rng is None else rng
    means = logs[rng.integers(0, logs.size, (BOOTSTRAP_DRAWS, logs.size))].mean(axis=1)
    low, high = np.exp(np.percentile(means, [2.5, 97.5]))
    return f"{np.exp(logs.mean()):.2f} [{low:.2f}, {high:.2f}]"


def paired_ratios(runs: list[Run]) -> list[str]:
    """calibcoach's error over each other method's on the same renders: the geometric mean of the
    per-render ratio with a 95% bootstrap interval, per cell and over every render.

    One render cannot tell two ways of reading it apart by 10%: at these error levels the truth
    error is set by the capture's distinct poses, and which frames of a hold reach the solve moves
    it by as much as the expected error E allows (README). The log-ratios of paired renders scatter
    by ~0.5-0.7, so only the mean over many renders, with its interval, says which is better.
    """
    rng = np.random.default_rng(0)  # the same interval every time the same runs are summarised
    cells = sorted({r.cell for r in runs}, key=list(CELLS).index)
    others = ["calibcoach --every-frame", "plain", "ROS-style", "mrcal"]
    error = {(r.cell, r.seed, r.method): r.error_px for r in runs}

    def interval(logs: np.ndarray) -> str:
        return "-" if logs.size == 0 else f"{geometric_mean_interval(np.exp(logs), rng)} (n {logs.size})"

    lines = ["", "calibcoach's error / the other method's on the same renders: geometric mean [95% bootstrap interval] "
             "(renders where both gave a finite error)", "",
             "| cell | " + " | ".join(f"/ {o}" for o in others) + " |", "|---|" + "---|" * len(others)]
    for label, chosen in [*((c, [c]) for c in cells), ("all renders", cells)]:
        row = []
        for other in others:
            logs = np.array([np.log(error[(c, s, "calibcoach")] / error[(c, s, other)])
                             for c, s, m in error if m == other and c in chosen
                             if np.isfinite(error.get((c, s, "calibcoach"), np.nan)) and np.isfinite(error[(c, s, m)])
                             and error[(c, s, m)] > 0])
            row.append(interval(logs))
        lines.append(f"| {label} | " + " | ".join(row) + " |")
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", nargs="+", default=list(CELLS), choices=list(CELLS))
    parser.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    parser.add_argument("--no-mrcal", action="store_true", help="leave mrcal out")
    parser.add_argument("--cached", action="store_true",
                        help="every render in bench/cache (any seed) of --cells (default: every cell) instead of --cells x --seeds")
    parser.add_argument("--calibcoach-only", action="store_true", help="only calibcoach's defaults and --every-frame")
    parser.add_argument("--out", default="heldout", help="results file stem in bench/results/")
    parser.add_argument("--merge", nargs="+", type=Path, help="only summarise these earlier .json results together")
    args = parser.parse_args()
    results = ROOT / "results"
    results.mkdir(exist_ok=True)
    runs: list[Run] = []
    if args.merge:  # runs measured in several processes (cells rendered at different times)
        runs = [Run(**r) for path in args.merge for r in json.loads(path.read_text())]
        args.cells = []
    chosen = ([(cell, seed) for cell, seed in cached_renders() if cell in args.cells] if args.cached and not args.merge
              else [(cell, seed) for cell in args.cells for seed in args.seeds])
    for cell, seed in chosen:
        for run in evaluate(cell, seed, use_mrcal=not args.no_mrcal, calibcoach_only=args.calibcoach_only):
            runs.append(run)
            (results / f"{args.out}.json").write_text(json.dumps([asdict(r) for r in runs], indent=1))  # kept if a later run dies
            print(f"{cell} s{seed} {run.method:26s} {run.error_px:8.4f} px  {run.frames:3d} frames  {run.outcome}"
                  f"  {run.seconds:6.1f} s  {json.dumps(run.extra)}", flush=True)
    (results / f"{args.out}.json").write_text(json.dumps([asdict(r) for r in runs], indent=1))
    text = "\n".join(summary(runs) + paired_ratios(runs))
    (results / f"{args.out}.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
