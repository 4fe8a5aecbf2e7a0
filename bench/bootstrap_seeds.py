"""The bootstrap solves' starting fields of view (70 deg pinhole, 150 deg fisheye), swept.

While a capture has 6-11 views, the session solves a reduced model (one focal length, the
principal point at the centre, k1 k2; `solve(..., reduced=True)`) from a field-of-view guess:
`BOOTSTRAP_SEED_HFOV_DEG` in app/solve/calibrate.py. Those guesses are starting points for
Levenberg-Marquardt, so what matters is whether they lie inside the basin that leads to the best
solution of the views at hand, on every lens, and by how much.

Views: the first 6, 8 and 11 of each capture, taken one a second (every 30th frame) where the
board passes the session's gate (>= 6 corners over two rows and two columns) --
  simulated: seven lenses (20, 30, 45, 70 deg pinhole at 720p, a 75 deg 1080p webcam, a 115 deg
             rational and a 150 deg fisheye), handheld paths careful / sloppy / frontal x 5 seeds, the
             board's corners projected through the true lens with 0.15 px of Gaussian noise;
  real:      the captures in ../shared/data (pycamset's three ~25 deg machine-vision cameras, the
             caliscope webcam, the wpical phone video, BoofCV's compact camera, read as a chessboard).
Each view set is solved from every seed (pinhole: 20-170 deg in 5 deg steps; fisheye: 60-240 deg
in 10 deg steps). The reference is the lowest-RMS solution any seed found; a seed "lands" when its
focal length is within 0.1% of the reference's. Reported per lens and model: how often the
default lands, the basin around the default (the widest run of landing seeds that contains it:
median and narrowest over the view sets), whether calibcoach's own rule (`solve(..., reduced=True)`
without a seed: 70 deg, and 35 deg too for a narrow reading) lands, and the focal error against the
truth from 70 deg alone and by the rule (careful and sloppy sets; frontal ones leave f loose).
~20 min on one core.

    .venv/bin/python bench/bootstrap_seeds.py [--data ../shared/data] [--quick]

Writes bench/results/bootstrap_seeds.md, and every solve to bench/cache/bootstrap_seeds.json (1.3 MB;
`--report-only` rewrites the report from it).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from calibcoach.app.solve.calibrate import BOOTSTRAP_SEED_HFOV_DEG, solve
from calibcoach.app.solve.result import View
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector, Detection
from calibcoach.coverage.select import SelectorSettings, corner_spread, spans_rows_and_columns
from calibcoach.drivers.errors import CalibrationError
from calibcoach.drivers.geometry import pose_matrix
from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.sim import LENSES
from calibcoach.drivers.sim_paths import handheld_path, image_points

ROOT = Path(__file__).resolve().parent
CACHE = ROOT / "cache"
SIZES = (6, 8, 11)  # MIN_VIEWS_FOR_INCREMENTAL_SOLVE .. FULL_MODEL_VIEWS - 1: the views a reduced solve sees
SEEDS_DEG = {"pinhole": np.arange(20.0, 171.0, 5.0), "fisheye": np.arange(60.0, 241.0, 10.0)}
LANDS = 1e-3  # relative focal-length difference to the best solution that counts as the same solution
NOISE_PX = 0.15


def _pinhole(size: tuple[int, int], hfov_deg: float, dist: list[float]) -> CameraModel:
    base = CameraModel.from_fov(size, hfov_deg)
    K = base.camera_matrix.copy()
    K[1, 1] *= 0.999  # square-ish pixels, not exactly square
    K[0, 2] += 3.0
    K[1, 2] -= 2.0
    return CameraModel("pinhole", K, np.array(dist, np.float64), size)


SIM_LENSES: dict[str, CameraModel] = {
    "tele20_720": _pinhole((1280, 720), 20.0, [0.02, -0.1, 0.0, 0.0, 0.0]),
    "tele30_720": _pinhole((1280, 720), 30.0, [0.05, -0.2, 0.0, 0.0, 0.0]),
    "narrow45_720": _pinhole((1280, 720), 45.0, [-0.06, 0.1, 0.0, 0.0, 0.0]),
    **{name: LENSES[name] for name in ("webcam720", "webcam1080", "wide720", "fisheye150")},
}


@dataclass
class ViewSet:
    lens: str
    source: str  # "sim careful s1", "real", ...
    size: tuple[int, int]
    views: list[View]
    truth_f: float | None  # the true (or published) focal length, px, where known


def _usable(corners_px: np.ndarray, ids: np.ndarray, object_points_m: np.ndarray, squares_x: int) -> bool:
    """The session's own gate: >= 6 corners spread over two rows and two columns (not collinear)."""
    det = Detection(corners_px.astype(np.float32), ids.astype(np.int32), object_points_m.astype(np.float32),
                    np.zeros(0, np.int32))
    settings = SelectorSettings()
    return det.corner_count >= settings.min_corners and corner_spread(det) >= settings.min_spread \
        and spans_rows_and_columns(det, squares_x)


def _sim_views(camera: CameraModel, spec: BoardSpec, style: str, seed: int) -> list[View]:
    """One view a second along a simulated handheld path: corners through the true lens, plus noise."""
    board = spec.cv_board()
    obj = np.asarray(board.getChessboardCorners(), np.float64).reshape(-1, 3)
    rng = np.random.default_rng(1000 + seed)
    views = []
    for pose in handheld_path(camera, spec, style, seconds=30.0, fps=30.0, seed=seed)[::30]:
        cam = obj @ pose_matrix(pose.rvec).T + pose.tvec
        px, seen = image_points(camera, cam)
        w, h = camera.image_size
        seen &= (px[:, 0] >= 0) & (px[:, 0] <= w - 1) & (px[:, 1] >= 0) & (px[:, 1] <= h - 1)
        ids = np.flatnonzero(seen).astype(np.int32)
        noisy = px[seen] + rng.normal(0.0, NOISE_PX, (int(seen.sum()), 2))
        if not _usable(noisy, ids, obj[seen], spec.squares_x):
            continue
        views.append(View(pose.index, "", ids, noisy, obj[seen]))
    return views


def _charuco_views(frames: list[np.ndarray], spec: BoardSpec) -> list[View]:
    detector = CharucoBoardDetector(spec)
    views = []
    for i, grey in enumerate(frames):
        det = detector.detect(grey)
        if _usable(det.corners_px, det.ids, det.object_points_m, spec.squares_x):
            views.append(View(i, "", det.ids, det.corners_px.astype(np.float64), det.object_points_m.astype(np.float64)))
    return views


def _video_greys(path: Path, every: int) -> list[np.ndarray]:
    capture = cv2.VideoCapture(str(path))
    greys, index = [], 0
    while True:
        ok, frame = capture.read()
        if not ok:
            return greys
        if index % every == 0:
            greys.append(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
        index += 1


def real_sets(data: Path) -> list[ViewSet]:
    """View sets from the real captures (skipped where ../shared/data is absent)."""
    sets: list[ViewSet] = []
    pycamset = data / "pycamset_charuco_3cam"
    published = {"1": 2840.4, "2": 2833.0, "3": 2856.6}  # the authors' (fx + fy) / 2
    if pycamset.is_dir():
        spec = BoardSpec(20, 20, 4.0, 3.2, "DICT_4X4_1000", False, None)
        for cam in ("1", "2", "3"):
            files = sorted((pycamset / cam).glob("*.jpg"), key=lambda p: int("".join(c for c in p.stem if c.isdigit()) or 0))
            greys = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
            sets.append(ViewSet(f"pycamset cam {cam} (~25 deg)", "real", greys[0].shape[::-1], _charuco_views(greys, spec), published[cam]))
    caliscope = data / "caliscope_webcam_charuco_4x5" / "video" / "cam_0.mp4"
    if caliscope.is_file():
        greys = _video_greys(caliscope, 1)
        spec = BoardSpec(4, 5, 54.0, 40.5, "DICT_4X4_1000", False, True)
        sets.append(ViewSet("caliscope webcam cam_0 (~90 deg)", "real", greys[0].shape[::-1], _charuco_views(greys[::4], spec), None))
    wpical = data / "wpical_phone_video_charuco_12x8" / "testcalibration.mp4"
    if wpical.is_file():
        greys = _video_greys(wpical, 10)
        spec = BoardSpec(12, 8, 15.585, 12.124, "DICT_5X5_1000", False, None)
        sets.append(ViewSet("wpical phone (frontal only)", "real", greys[0].shape[::-1], _charuco_views(greys, spec), None))
    boofcv = data / "boofcv_sony_hx5v_chess"
    if boofcv.is_dir():
        obj = np.zeros((6 * 4, 3))
        obj[:, :2] = np.mgrid[0:6, 0:4].T.reshape(-1, 2) * 0.03
        views = []
        for i, f in enumerate(sorted(boofcv.glob("frame*.jpg"))):
            grey = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            found, corners = cv2.findChessboardCornersSB(grey, (6, 4))
            if found:
                views.append(View(i, f.name, np.arange(24, dtype=np.int32), corners.reshape(-1, 2).astype(np.float64), obj))
        sets.append(ViewSet("BoofCV Sony HX5V (chessboard)", "real", (640, 480), views, 699.8))
    return [s for s in sets if len(s.views) >= SIZES[0]]


def sweep(views: list[View], size: tuple[int, int], model: str) -> list[tuple[float, float | None, float]]:
    """(seed, focal length, RMS) for every seed of `model`; (seed, None, inf) where the solve failed or
    gave a field of view no lens has (a pinhole over 175 deg, a fisheye over 250: degenerate fits)."""
    out = []
    for seed in SEEDS_DEG[model]:
        try:
            sol = solve(views, size, model, reduced=True, seed_hfov_deg=float(seed))
        except CalibrationError:
            out.append((float(seed), None, float("inf")))
            continue
        hfov = sol.camera.field_of_view_deg()[0]
        plausible = np.isfinite(hfov) and 1.0 < hfov < (175.0 if model == "pinhole" else 250.0)
        out.append((float(seed), float(sol.camera.fx), float(sol.rms_px)) if plausible else (float(seed), None, float("inf")))
    return out


def _best(results: list[tuple[float, float | None, float]], seeds: tuple[float, ...] | None = None) -> tuple[float, float | None, float]:
    """The lowest-RMS result (among `seeds` only, when given)."""
    chosen = [r for r in results if seeds is None or r[0] in seeds]
    return min(chosen, key=lambda r: r[2])


def basin(results: list[tuple[float, float | None, float]], default: float) -> dict:
    """Which seeds land on the best solution, and the run of landing seeds around `default`."""
    best = _best(results)
    if best[1] is None:
        return {"best_f": None, "best_rms": None, "default_lands": False, "basin": None, "landing_share": 0.0, "sweep": results}
    lands = [r[1] is not None and abs(r[1] / best[1] - 1.0) < LANDS for r in results]
    seeds = [r[0] for r in results]
    i = int(np.argmin(np.abs(np.array(seeds) - default)))
    run = None
    if lands[i]:
        lo = hi = i
        while lo > 0 and lands[lo - 1]:
            lo -= 1
        while hi < len(seeds) - 1 and lands[hi + 1]:
            hi += 1
        run = (seeds[lo], seeds[hi])
    return {"best_f": best[1], "best_rms": best[2], "default_lands": bool(lands[i]), "basin": run,
            "landing_share": float(np.mean(lands)), "sweep": results}


def lands_with(row: dict, seeds: tuple[float, ...]) -> bool:
    """Whether the lowest-RMS of the solves from `seeds` is the best solution of the sweep."""
    if row["best_f"] is None:
        return False
    f = _best([tuple(r) for r in row["sweep"]], seeds)[1]
    return f is not None and abs(f / row["best_f"] - 1.0) < LANDS


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent.parent / "shared" / "data")
    parser.add_argument("--quick", action="store_true", help="one seed per style, no real captures")
    parser.add_argument("--report-only", action="store_true", help="rewrite the report from bench/cache/bootstrap_seeds.json")
    args = parser.parse_args()
    if args.report_only:
        _report_only(CACHE / "bootstrap_seeds.json")
        return 0
    cv2.setNumThreads(1)  # tiny solves: OpenCV's threads only add overhead (the numbers are the same)
    spec = BoardSpec()
    sets: list[ViewSet] = []
    for name, camera in SIM_LENSES.items():
        for style in ("careful", "sloppy", "frontal"):
            for seed in (1,) if args.quick else (1, 2, 3, 4, 5):
                sets.append(ViewSet(name, f"sim {style} s{seed}", camera.image_size, _sim_views(camera, spec, style, seed),
                                    0.5 * (camera.fx + camera.fy)))
    if not args.quick:
        if args.data.is_dir():
            sets += real_sets(args.data)
        else:
            print(f"bootstrap_seeds: no {args.data}: the real captures are left out", file=sys.stderr)
    rows = []
    for n, s in enumerate(sets):
        for k in SIZES:
            if len(s.views) < k:
                continue
            for model in ("pinhole", "fisheye"):
                result = basin(sweep(s.views[:k], s.size, model), BOOTSTRAP_SEED_HFOV_DEG[model])
                try:  # what calibcoach itself does (the default start, and for a narrow reading a second one)
                    rule_f: float | None = float(solve(s.views[:k], s.size, model, reduced=True).camera.fx)
                except CalibrationError:
                    rule_f = None
                rows.append({"lens": s.lens, "source": s.source, "views": k, "model": model, "truth_f": s.truth_f,
                             "rule_f": rule_f, **result})
        print(f"\r{n + 1}/{len(sets)} view sets", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    CACHE.mkdir(exist_ok=True)
    (CACHE / "bootstrap_seeds.json").write_text(json.dumps(rows) + "\n")
    (ROOT / "results" / "bootstrap_seeds.md").write_text(report(rows))
    print(report(rows))
    return 0


ALWAYS_BOTH = (70.0, 35.0)  # the pinhole's two starts solved every time, for comparison with the rule


def _default_f(row: dict) -> float | None:
    return next(f for seed, f, _rms in row["sweep"] if seed == BOOTSTRAP_SEED_HFOV_DEG[row["model"]])


def _off(f: float | None, truth: float) -> float:
    return float("inf") if f is None else abs(f / truth - 1.0)


def report(rows: list[dict]) -> str:
    lines = [
        "# The bootstrap solves' starting fields of view, swept",
        "",
        "`bench/bootstrap_seeds.py` (its docstring says how). \"Lands\": the solve from that start reaches the",
        "lowest-RMS solution any start found (focal length within 0.1%). \"calibcoach's rule\": 70 deg, and",
        "for a reading under 50 deg also 35 deg, the clearly better fit kept (app/solve/calibrate.py).",
        "",
        "| lens | model | view sets | default lands | basin around the default: median | narrowest | "
        "calibcoach's rule lands (always 70 & 35: lands) | f vs truth, careful & sloppy: 70 deg alone median / worst | "
        "calibcoach's rule median / worst |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for lens in dict.fromkeys(r["lens"] for r in rows):
        for model in ("pinhole", "fisheye"):
            mine = [r for r in rows if r["lens"] == lens and r["model"] == model and r["best_f"] is not None]
            if not mine:
                continue
            landed = [r for r in mine if r["default_lands"]]
            runs = [r["basin"] for r in landed if r["basin"] is not None]
            median = f"{np.median([a for a, _ in runs]):.0f}-{np.median([b for _, b in runs]):.0f} deg" if runs else "-"
            narrowest = f"{max(a for a, _ in runs):.0f}-{min(b for _, b in runs):.0f} deg" if runs else "-"
            rule = sum(r["rule_f"] is not None and abs(r["rule_f"] / r["best_f"] - 1.0) < LANDS for r in mine)
            both = f" ({sum(lands_with(r, ALWAYS_BOTH) for r in mine)}/{len(mine)})" if model == "pinhole" else ""
            observable = [r for r in mine if r["truth_f"] and "frontal" not in r["source"]]  # frontal views leave f loose
            alone = by_rule = ""
            if model == "pinhole" and observable:
                a = [_off(_default_f(r), r["truth_f"]) for r in observable]
                b = [_off(r["rule_f"], r["truth_f"]) for r in observable]
                alone = f"{100 * np.median(a):.1f}% / {100 * max(a):.1f}%"
                by_rule = f"{100 * np.median(b):.1f}% / {100 * max(b):.1f}%"
            lines.append(f"| {lens} | {model} | {len(mine)} | {len(landed)}/{len(mine)} | {median} | {narrowest} | "
                         f"{rule}/{len(mine)}{both} | {alone} | {by_rule} |")
    missed = [r for r in rows if r["best_f"] is not None and not r["default_lands"]]
    unsolvable = sum(r["best_f"] is None for r in rows)
    lines += ["", (f"{unsolvable} sweeps found no plausible solution from any seed. " if unsolvable else "")
              + f"The default start missed the best solution in {len(missed)} of {len(rows) - unsolvable} sweeps" + (":" if missed else ".")]
    for r in missed:
        got = _default_f(r)
        default = f"f {got:.0f} px" if got is not None else "failed"
        rule = "failed" if r["rule_f"] is None else f"f {r['rule_f']:.0f} px"
        lines.append(f"- {r['lens']}, {r['source']}, {r['views']} views, {r['model']}: best f {r['best_f']:.0f} px "
                     f"(RMS {r['best_rms']:.2f} px); from {BOOTSTRAP_SEED_HFOV_DEG[r['model']]:.0f} deg: {default}; "
                     f"calibcoach's rule: {rule}; {100 * r['landing_share']:.0f}% of the seeds land")
    return "\n".join(lines) + "\n"


def _report_only(path: Path) -> None:
    """Rewrite the report from a saved bootstrap_seeds.json (the sweep takes ~20 min)."""
    rows = json.loads(path.read_text())
    (ROOT / "results" / "bootstrap_seeds.md").write_text(report(rows))


if __name__ == "__main__":
    raise SystemExit(main())
