"""Re-detection on a local view (coverage/local_view.py): frames and corners recovered, and their error.

For rendered handheld captures (several seeds, careful and sloppy hands, optionally low light)
through the 150 deg fisheye, the 115 deg wide lens and the 70 deg webcam, every sharp frame
(no motion during the exposure) is detected plainly and then offered to the session's
`Redetector` (the same policy the pipeline uses) with three lens estimates:

- truth: the lens the frames were rendered through;
- early solve: the reduced solve on the capture's first 8 frames with 20+ plainly found corners,
  as the session's first incremental solve would have it;
- guess: the field-of-view guess the session re-detects with before any solve
  (`CalibrationSession.detection_lens`, hfov_guess_deg set to the lens's nominal field of view).

Reported per lens: sharp frames with >= 20 corners truly in view; of those, where plain detection
found < 6; how many of those re-detection brings to >= 6 corners; the corners recovered; their
error against the true corner positions next to the error of plainly found corners (median,
95th percentile, max); and the time per re-detection. Corners off by more than 2 px are counted
as wrong (a wrong id or a false corner).

Renders are cached in bench/cache/redetect/ (git-ignored): ~0.5 s per 720p frame.

`--replay RECORDING ...` also runs the whole pipeline on recordings (e.g. bench/accuracy.py's cached
fisheye renders) with re-detection and with it gated off.

    .venv/bin/python bench/redetect.py [--seconds 20] [--fps 4] [--seeds 1 2 3] [--replay bench/cache/...]

Writes bench/results/redetect.md and prints the table.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from calibcoach.app.replay import run_replay
from calibcoach.app.session import CalibrationSession, SessionSettings
from calibcoach.app.solve.calibrate import solve
from calibcoach.app.solve.compare import projection_difference
from calibcoach.app.solve.result import View
from calibcoach.app.solve.uncertainty import covered_region_mask
from calibcoach.coverage import redetect
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector
from calibcoach.coverage.local_view import redetect_in_local_view
from calibcoach.coverage.redetect import FEW_CORNERS, WIDE_LENS_DEG, Redetector
from calibcoach.drivers.geometry import pose_matrix
from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.recording import read_truth
from calibcoach.drivers.replay import open_source
from calibcoach.drivers.sim import LENSES, SimulatedCamera, handheld_trajectory

ROOT = Path(__file__).resolve().parent
NOMINAL_FOV = {"fisheye150": 150.0, "wide720": 115.0, "webcam720": 70.0}
MIN_TRUE_CORNERS = 20
WRONG_PX = 2.0


@dataclass
class Tally:
    frames: int = 0  # sharp frames with >= MIN_TRUE_CORNERS corners in view
    lost: int = 0  # of those, plain detection < FEW_CORNERS
    tried: int = 0  # frames the policy re-detected (lost or partial)
    recovered: int = 0  # lost frames brought to >= FEW_CORNERS
    corners: int = 0  # corners added on recovered frames
    added_partial: int = 0  # corners added on frames plain detection had already made usable
    errors_recovered: list = field(default_factory=list)  # px, corners added to recovered lost frames
    errors_partial: list = field(default_factory=list)  # px, corners added to frames plain detection made usable
    errors_plain_same: list = field(default_factory=list)  # px, plain corners of the frames re-detection improved
    wrong: int = 0  # corners of improved detections more than WRONG_PX from the truth
    seconds: list = field(default_factory=list)


def render(lens: str, style: str, seed: int, *, seconds: float, fps: float, low_light: bool) -> dict:
    tag = f"{lens}_{style}_s{seed}_{seconds:g}s_{fps:g}fps{'_dim' if low_light else ''}"
    path = ROOT / "cache" / "redetect" / f"{tag}.npz"
    if path.exists():
        return dict(np.load(path))
    camera, spec = LENSES[lens], BoardSpec()
    trajectory = handheld_trajectory(camera, spec, style, seconds=seconds, seed=seed)
    poses = trajectory.sample(seconds=seconds, fps=fps)
    source = SimulatedCamera(camera, spec, poses, seed=seed, lens_name=lens, trajectory=trajectory, low_light=low_light)
    start = time.perf_counter()
    images = np.array([frame.grey() for frame in source])
    sharp = np.array([len(source.exposure_poses(i)) == 1 for i in range(len(poses))])
    print(f"rendered {tag}: {len(poses)} frames in {time.perf_counter() - start:.0f} s", flush=True)
    data = {"images": images, "rvecs": np.array([p.rvec for p in poses]), "tvecs": np.array([p.tvec for p in poses]),
            "sharp": sharp}
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **data)
    return data


def truth_px(camera: CameraModel, rvec: np.ndarray, tvec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    points = BoardSpec().corner_points_m() @ pose_matrix(rvec).T + tvec
    px = camera.project(points)
    w, h = camera.image_size
    inside = (points[:, 2] > 0) & (px[:, 0] >= 0) & (px[:, 0] <= w - 1) & (px[:, 1] >= 0) & (px[:, 1] <= h - 1)
    return px, inside


def early_solve(camera: CameraModel, plain: list, model: str, fallback: CameraModel) -> CameraModel:
    """The reduced solve on the first 8 frames with 20+ corners (or the 8 richest with 6+; the guess without 3)."""
    usable = [(i, d) for i, d in enumerate(plain) if d.corner_count >= FEW_CORNERS]
    chosen = [(i, d) for i, d in usable if d.corner_count >= MIN_TRUE_CORNERS][:8]
    if len(chosen) < 3:  # a blurred capture (low light, sloppy): the richest frames there are
        chosen = sorted(usable, key=lambda item: -item[1].corner_count)[:8]
    if len(chosen) < 3:
        return fallback
    views = [View(i, "", d.ids, d.corners_px.astype(np.float64), d.object_points_m.astype(np.float64)) for i, d in chosen]
    return solve(views, camera.image_size, model, reduced=True).camera


def run(lens: str, style: str, seed: int, args, tallies: dict[str, Tally], plain_errors: list, refine_errors: list) -> None:
    data = render(lens, style, seed, seconds=args.seconds, fps=args.fps, low_light=args.low_light)
    camera = LENSES[lens]
    spec = BoardSpec().with_detected(legacy=False, inverted=False)
    detector = CharucoBoardDetector(spec)
    plain = [detector.detect(g) for g in data["images"]]
    guess = CalibrationSession(spec, camera.image_size, SessionSettings(hfov_guess_deg=NOMINAL_FOV[lens])).detection_lens
    lenses = {"truth": camera, "early solve": early_solve(camera, plain, camera.model, guess), "guess": guess}
    if lens == "webcam720":  # would the view help a narrow lens too? (the policy says it is not worth trying)
        lenses["truth, wide-lens gate off"] = camera
    for name, estimate in lenses.items():
        tally = tallies.setdefault(name, Tally())
        redetector = Redetector(spec)
        redetect.WIDE_LENS_DEG = 0.0 if name.endswith("gate off") else WIDE_LENS_DEG
        for i, grey in enumerate(data["images"]):
            truth, inside = truth_px(camera, data["rvecs"][i], data["tvecs"][i])
            first = plain[i]
            before = redetector.counts.tried
            start = time.perf_counter()
            better = redetector.improve(i, grey, first, estimate)
            seconds = time.perf_counter() - start
            tried = redetector.counts.tried > before
            if not (data["sharp"][i] and inside.sum() >= MIN_TRUE_CORNERS):
                continue
            tally.frames += 1
            if name == "truth" and first.corner_count:
                plain_errors.extend(np.linalg.norm(first.corners_px - truth[first.ids], axis=1))
            lost = first.corner_count < FEW_CORNERS
            tally.lost += lost
            if tried:
                tally.tried += 1
                tally.seconds.append(seconds)
            if better is first:
                continue
            added = ~np.isin(better.ids, first.ids)
            error = np.linalg.norm(better.corners_px - truth[better.ids], axis=1)
            tally.wrong += int(np.sum(error > WRONG_PX))
            tally.errors_plain_same.extend(np.linalg.norm(first.corners_px - truth[first.ids], axis=1))
            if lost and better.corner_count >= FEW_CORNERS:
                tally.recovered += 1
                tally.corners += better.corner_count
                tally.errors_recovered.extend(error[added])
            elif not lost:
                tally.added_partial += int(added.sum())
                tally.errors_partial.extend(error[added])
            if name == "truth" and lost:  # the same frames refined again in the frame, for the module's docstring
                again = redetect_in_local_view(grey, estimate, detector, first, refine=True)
                if again is not None:
                    new = ~np.isin(again.detection.ids, first.ids)
                    refine_errors.extend(np.linalg.norm(again.detection.corners_px[new] - truth[again.detection.ids[new]], axis=1))


def replay_with_and_without(recording: Path) -> list[str]:
    """The whole pipeline (run_replay + finish) on a recording, with re-detection and with it gated off."""
    truth = read_truth(recording).camera
    rows = []
    for label, gate in (("with re-detection", WIDE_LENS_DEG), ("without", float("inf"))):
        redetect.WIDE_LENS_DEG = gate
        source = open_source(recording)
        start = time.perf_counter()
        session, replay_stats = run_replay(source, BoardSpec.from_dict(dict(source.info.board)), SessionSettings())
        result = session.finish()
        seconds = time.perf_counter() - start
        cal = result.calibration
        mask = covered_region_mask(truth.image_size, [v.image_points_px for v in cal.views], (32, 18))
        covered = projection_difference(truth, cal.camera, grid=(32, 18), mask=mask)
        whole = projection_difference(truth, cal.camera, grid=(32, 18))
        counts = replay_stats.redetection
        done = "-" if counts is None or gate == float("inf") else f"{counts.tried} / {counts.recovered} / {counts.corners_added}"
        rows.append(f"| {recording.name} | {label} | {replay_stats.frames_read} | {done} | "
                    f"{result.rejections.get('too few corners', 0) + result.rejections.get('no board', 0)} | {len(cal.views)} | "
                    f"{cal.corner_count} | {result.coverage.completeness():.3f} | {covered.p95_px:.3f} | {whole.p95_px:.3f} | "
                    f"{result.verdict.grade} | {seconds:.0f} |")
        print(rows[-1], flush=True)
    redetect.WIDE_LENS_DEG = WIDE_LENS_DEG
    return rows


def stats(values) -> str:
    v = np.asarray(values, np.float64)
    if v.size == 0:
        return "-"
    return f"{np.median(v):.3f} / {np.percentile(v, 95):.3f} / {v.max():.3f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--fps", type=float, default=4.0)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--lenses", nargs="+", default=["fisheye150", "wide720", "webcam720"])
    parser.add_argument("--low-light-seed", type=int, default=1, help="also a low-light capture per style at this seed")
    parser.add_argument("--replay", type=Path, nargs="*", default=[], help="recordings to replay with and without re-detection")
    args = parser.parse_args()
    cv2.setNumThreads(1)  # as in the session
    lines = ["# Re-detection on a local view (bench/redetect.py)", "",
             f"Rendered handheld captures, {args.seconds:g} s at {args.fps:g} fps, seeds {args.seeds} x careful/sloppy "
             f"(+ low light, seed {args.low_light_seed}). Frames: sharp (no motion in the exposure) with >= "
             f"{MIN_TRUE_CORNERS} corners truly in view. Lost: plain detection found < {FEW_CORNERS}. Errors against the "
             "true corner positions, px, median / 95th pct / max.", "",
             "| lens | lens estimate | frames | lost | re-detected | recovered (>= 6) | corners on recovered | "
             "corners added to usable frames | wrong (> 2 px) | ms per re-detection (median / max) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    errors = ["", "Errors against the true corner positions, px (median / 95th pct / max): corners re-detection added "
              "to recovered frames and to usable frames; the plain corners of the same frames (harder frames than "
              "most: far and steep boards); plain corners over all frames.", "",
              "| lens | lens estimate | added, recovered frames | added, usable frames | plain, same frames | "
              "plain, all frames |", "|---|---|---|---|---|---|"]
    refine_all: list = []
    for lens in args.lenses:
        tallies = {name: Tally() for name in ("truth", "early solve", "guess")}
        plain_errors: list = []
        for style in ("careful", "sloppy"):
            runs = [(seed, False) for seed in args.seeds] + [(args.low_light_seed, True)]
            for seed, dim in runs:
                args.low_light = dim
                run(lens, style, seed, args, tallies, plain_errors, refine_all if lens == "fisheye150" else [])
        for name, t in tallies.items():
            ms = f"{1000 * np.median(t.seconds):.0f} / {1000 * np.max(t.seconds):.0f}" if t.seconds else "-"
            lines.append(f"| {lens} | {name} | {t.frames} | {t.lost} | {t.tried} | {t.recovered} | {t.corners} | "
                         f"{t.added_partial} | {t.wrong} | {ms} |")
            errors.append(f"| {lens} | {name} | {stats(t.errors_recovered)} | {stats(t.errors_partial)} | "
                          f"{stats(t.errors_plain_same)} | {stats(plain_errors)} |")
            print(lines[-1], errors[-1], sep="\n", flush=True)
    lines += errors
    if args.replay:
        lines += ["", "Whole pipeline (`run_replay` + `finish`), with re-detection and with it gated off. Re-detected: frames "
                  "tried / lost frames recovered / corners added. Errors against the true lens, px (95th percentile over the "
                  "covered region and over the whole image).", "",
                  "| recording | | frames read | re-detected | no board + too few corners | views | corners | coverage | "
                  "covered p95 | whole p95 | verdict | s |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for recording in args.replay:
            lines += replay_with_and_without(recording)
    lines += ["", f"Refined again in the frame (`refine=True`, fisheye, true lens, lost frames): {stats(refine_all)} px "
              f"over {len(refine_all)} corners."]
    (ROOT / "results" / "redetect.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
