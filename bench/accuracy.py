"""Accuracy and frame efficiency: calibcoach against what users would do otherwise, in one run.

For simulated captures with known lenses (careful, sloppy and frontal-only hands), three ways to
calibrate from the same frames:
  (a) the method's plain recipe: every Nth frame with >= 6 corners into calibrateCamera
      (cv2.fisheye.calibrate for the fisheye), N chosen so that about 60 frames go in;
  (b) a ROS-camera_calibration-style selector: a frame is kept when its (x, y, size, skew) differs
      from every kept one by more than 0.2 (L1), until the bars are full or 40 frames are kept;
  (c) calibcoach (`run_replay` + `finish`).
Each result is scored by its projection error against the lens truth over the image region the
board covered (after the one rotation any extrinsic absorbs), with the frames it used and whether
it accepted a calibration that is off by more than 0.5 px there.

Rendering costs ~0.4 s per 720p frame, so rendered sessions are cached as recordings in
bench/cache/ (git-ignored). Usage:

    .venv/bin/python bench/accuracy.py [--only webcam720_careful] [--seconds 30] [--fps 8]

Writes bench/results/accuracy.md and prints the same table.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from calibcoach.app.replay import run_replay
from calibcoach.app.session import SessionSettings
from calibcoach.app.solve.compare import projection_difference
from calibcoach.app.solve.uncertainty import covered_region_mask
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector, Detection
from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.recording import RecordingWriter, read_truth, write_truth
from calibcoach.drivers.replay import open_source
from calibcoach.drivers.sim import LENSES, SimulatedCamera, handheld_trajectory

ROOT = Path(__file__).resolve().parent  # a bench script may find its own folder; the package never does
SESSIONS = [(lens, style) for lens in ("webcam720", "wide720", "fisheye150") for style in ("careful", "sloppy", "frontal")]
BAD_PX = 0.5


def rendered(lens: str, style: str, *, seconds: float, fps: float) -> Path:
    folder = ROOT / "cache" / f"{lens}_{style}_{seconds:g}s_{fps:g}fps"
    if (folder / "truth.json").exists():
        return folder
    spec = BoardSpec()
    camera = LENSES[lens]
    trajectory = handheld_trajectory(camera, spec, style, seconds=seconds, seed=7)
    poses = trajectory.sample(seconds=seconds, fps=fps)
    source = SimulatedCamera(camera, spec, poses, seed=7, lens_name=lens, trajectory=trajectory)
    start = time.perf_counter()
    with RecordingWriter(folder, camera_id=source.info.camera_id, kind="sim", image_size=camera.image_size, fps=fps,
                         controls={}, board=spec.to_dict()) as writer:
        for frame in source:
            writer.write(frame)
    write_truth(folder, camera, [(p.index, p.rvec, p.tvec) for p in poses])
    print(f"rendered {folder.name}: {len(poses)} frames in {time.perf_counter() - start:.0f} s")
    return folder


def detections(folder: Path) -> list[Detection]:
    detector = CharucoBoardDetector(BoardSpec())
    return [detector.detect(frame.grey()) for frame in open_source(folder)]


def solve_plain(views: list[Detection], camera: CameraModel) -> CameraModel:
    obj = [d.object_points_m.reshape(-1, 1, 3).astype(np.float64) for d in views]
    img = [d.corners_px.reshape(-1, 1, 2).astype(np.float64) for d in views]
    if camera.model == "fisheye":
        _, K, D, _, _ = cv2.fisheye.calibrate([o.reshape(1, -1, 3) for o in obj], [i.reshape(1, -1, 2) for i in img],
                                              camera.image_size, None, None,
                                              flags=cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW)
        return CameraModel("fisheye", K, D.reshape(-1), camera.image_size)
    flags = cv2.CALIB_RATIONAL_MODEL if camera.model == "rational" else 0
    _, K, D, _, _ = cv2.calibrateCamera([o.astype(np.float32) for o in obj], [i.astype(np.float32) for i in img],
                                        camera.image_size, None, None, flags=flags)
    n = 8 if camera.model == "rational" else 5
    return CameraModel(camera.model, K, D.reshape(-1)[:n], camera.image_size)


def ros_params(d: Detection, size: tuple[int, int]) -> np.ndarray:
    """ROS camera_calibration's sample parameters: x, y, size and skew of the board, each 0..1."""
    w, h = size
    pts = d.corners_px
    hull = cv2.convexHull(pts.reshape(-1, 1, 2).astype(np.float32)).reshape(-1, 2)
    area = cv2.contourArea(hull.astype(np.float32))
    rect = cv2.minAreaRect(pts.astype(np.float32))
    skew = 1.0 - min(1.0, area / max(rect[1][0] * rect[1][1], 1e-9))
    return np.array([pts[:, 0].mean() / w, pts[:, 1].mean() / h, np.sqrt(area / (w * h)), skew])


def select_ros(dets: list[Detection], size: tuple[int, int]) -> list[Detection]:
    kept: list[Detection] = []
    params: list[np.ndarray] = []
    for d in dets:
        if d.corner_count < 6:
            continue
        p = ros_params(d, size)
        if not params or min(np.abs(p - q).sum() for q in params) > 0.2:
            kept.append(d)
            params.append(p)
        ranges = np.ptp(np.array(params), axis=0) if len(params) > 1 else np.zeros(4)
        if len(kept) >= 40 or np.all(ranges >= [0.7, 0.7, 0.4, 0.5]):  # ROS: bars full, or enough
            break
    return kept


def score(truth: CameraModel, estimate: CameraModel, corner_sets: list[np.ndarray]) -> float:
    mask = covered_region_mask(truth.image_size, corner_sets, (32, 18))
    return projection_difference(truth, estimate, grid=(32, 18), mask=mask).rms_px


def evaluate(folder: Path) -> list[tuple[str, float, int, str]]:
    truth = read_truth(folder).camera
    dets = detections(folder)
    usable = [d for d in dets if d.corner_count >= 6]
    rows = []
    step = max(1, len(usable) // 60)
    plain = usable[::step][:60]
    for name, chosen in (("plain every Nth", plain), ("ROS-style", select_ros(dets, truth.image_size))):
        try:
            err = score(truth, solve_plain(chosen, truth), [d.corners_px for d in chosen])
        except cv2.error as exc:
            rows.append((name, float("nan"), len(chosen), f"crashed: {str(exc).strip().splitlines()[-1][:60]}"))
            continue
        rows.append((name, err, len(chosen), "accepted" + (" (BAD)" if err > BAD_PX else "")))
    source = open_source(folder)
    session, _ = run_replay(source, BoardSpec.from_dict(dict(source.info.board)), SessionSettings())
    result = session.finish()
    err = score(truth, result.calibration.camera, [v.image_points_px for v in result.calibration.views])
    verdict = result.verdict.grade + (" (BAD)" if result.verdict.trusted and err > BAD_PX else "")
    rows.append(("calibcoach", err, len(result.calibration.views), verdict))
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", help="one session, e.g. webcam720_careful")
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--fps", type=float, default=8.0)
    args = parser.parse_args()
    lines = ["| session | method | projection error vs truth, px | frames | outcome |", "|---|---|---|---|---|"]
    for lens, style in SESSIONS:
        if args.only and args.only != f"{lens}_{style}":
            continue
        folder = rendered(lens, style, seconds=args.seconds, fps=args.fps)
        for method, err, frames, outcome in evaluate(folder):
            line = f"| {lens} {style} | {method} | {err:.4f} | {frames} | {outcome} |"
            print(line, flush=True)
            lines.append(line)
    out = ROOT / "results" / "accuracy.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
