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
it accepted a calibration that is off by more than 0.5 px there (or 2 px over the whole image).

Frame efficiency: each method's frames in the order it took them, solved with the plain
calibrateCamera after 6, 8, 10 ... 60 frames and scored over the region every usable frame of the
capture covered (a common yardstick, so a method that never leaves the centre cannot look good by
being judged only where it looked). Reported: frames needed to reach 0.1 px, and the curves.

Rendering costs ~0.4 s per 720p frame, so rendered sessions are cached as recordings in
bench/cache/ (git-ignored). `--seed` renders captures no run has seen before. Usage:

    .venv/bin/python bench/accuracy.py [--only webcam720_careful] [--seconds 30] [--fps 8] [--seed 7]

Writes bench/results/accuracy.md, bench/results/efficiency_<session>.png and prints the tables.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from dataclasses import dataclass
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
sys.path.insert(0, str(ROOT))  # bench/plots.py
SESSIONS = [(lens, style) for lens in ("webcam720", "wide720", "fisheye150") for style in ("careful", "sloppy", "frontal")]
BAD_PX = 0.5  # px over the region the board covered
BAD_WHOLE_PX = 2.0  # px over the whole image


def rendered(lens: str, style: str, *, seconds: float, fps: float, seed: int = 7) -> Path:
    suffix = "" if seed == 7 else f"_seed{seed}"  # seed 7's folders predate the option
    folder = ROOT / "cache" / f"{lens}_{style}_{seconds:g}s_{fps:g}fps{suffix}"
    if (folder / "truth.json").exists():
        return folder
    camera = LENSES[lens]
    poses = render_recording(folder, camera, lens_name=lens, style=style, seconds=seconds, fps=fps, seed=seed)
    write_truth(folder, camera, [(p.index, p.rvec, p.tvec) for p in poses])
    return folder


def render_recording(folder: Path, camera: CameraModel, *, lens_name: str, style: str, seconds: float, fps: float,
                     seed: int) -> list:
    """Render a handheld capture of the default board into a recording at `folder`; returns its poses."""
    spec = BoardSpec()
    trajectory = handheld_trajectory(camera, spec, style, seconds=seconds, seed=seed)
    poses = trajectory.sample(seconds=seconds, fps=fps)
    source = SimulatedCamera(camera, spec, poses, seed=seed, lens_name=lens_name, trajectory=trajectory)
    start = time.perf_counter()
    with RecordingWriter(folder, camera_id=source.info.camera_id, kind="sim", image_size=camera.image_size, fps=fps,
                         controls={}, board=spec.to_dict()) as writer:
        for frame in source:
            writer.write(frame)
    print(f"rendered {folder.name}: {len(poses)} frames in {time.perf_counter() - start:.0f} s")
    return poses


def detections(folder: Path) -> dict[int, Detection]:
    """Every frame's detection, by frame index."""
    detector = CharucoBoardDetector(BoardSpec())
    return {frame.index: detector.detect(frame.grey()) for frame in open_source(folder)}


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


def crash_note(exc: Exception) -> str:
    """A table cell for a baseline OpenCV refused: "crashed: <what it asserted> in <function>".

    OpenCV's message leads with its build's source path and line, which filled the cell before the
    assertion (a plain recipe whose frame had 10 corners in a line: `matH0.size() == Size(3, 3) in
    initIntrinsicParams2D`, the homography it cannot fit)."""
    text = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
    asserted = re.search(r"\(-?\d+:[^)]*\)\s*(.*?)\s+in function '([^']+)'", text)
    return f"crashed: {asserted.group(1)} in {asserted.group(2)}" if asserted else f"crashed: {text[:60]}"


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


def whole_image_error(truth: CameraModel, estimate: CameraModel) -> float:
    """RMS error over the whole image: what the user meets at the edges the capture never reached."""
    return projection_difference(truth, estimate, grid=(32, 18)).rms_px


def is_bad(covered_px: float, whole_px: float) -> bool:
    return covered_px > BAD_PX or whole_px > BAD_WHOLE_PX


@dataclass
class Method:
    """One way of calibrating a capture: the frames it took, in the order it took them."""

    name: str
    frames: list[Detection]
    error_px: float = float("nan")  # against the truth over the region its own frames covered
    whole_px: float = float("nan")  # against the truth over the whole image
    outcome: str = ""
    curve: tuple[list[int], list[float]] = ((), ())  # frames used -> error over the capture's whole covered region


PREFIXES = (6, 8, 10, 12, 15, 20, 25, 30, 40, 50, 60)
EFFICIENCY_TARGET_PX = 0.1


def efficiency_curve(truth: CameraModel, frames: list[Detection], yardstick: list[np.ndarray]) -> tuple[list[int], list[float]]:
    """Error against the truth after the first k frames, over the region the whole capture covered."""
    mask = covered_region_mask(truth.image_size, yardstick, (32, 18))
    ks, errors = [], []
    for k in PREFIXES:
        if k > len(frames):
            break
        try:
            estimate = solve_plain(frames[:k], truth)
            errors.append(projection_difference(truth, estimate, grid=(32, 18), mask=mask).rms_px)
        except cv2.error:
            errors.append(float("nan"))
        ks.append(k)
    return ks, errors


def frames_to_target(curve: tuple[list[int], list[float]]) -> str:
    """The first prefix from which the error stays at or under the target ("never" if it does not get there)."""
    ks, errors = curve
    for i, k in enumerate(ks):
        if all(np.isfinite(e) and e <= EFFICIENCY_TARGET_PX for e in errors[i:]):
            return str(k)
    return "never"


def evaluate(folder: Path) -> list[Method]:
    truth = read_truth(folder).camera
    dets = detections(folder)
    usable = [d for d in dets.values() if d.corner_count >= 6]
    step = max(1, len(usable) // 60)
    methods = [Method("plain every Nth", usable[::step][:60]), Method("ROS-style", select_ros(list(dets.values()), truth.image_size))]
    for method in methods:
        try:
            estimate = solve_plain(method.frames, truth)
            method.error_px = score(truth, estimate, [d.corners_px for d in method.frames])
            method.whole_px = whole_image_error(truth, estimate)
            method.outcome = "accepted" + (" (BAD)" if is_bad(method.error_px, method.whole_px) else "")
        except cv2.error as exc:
            method.outcome = crash_note(exc)
    source = open_source(folder)
    session, _ = run_replay(source, BoardSpec.from_dict(dict(source.info.board)), SessionSettings())
    live_order = [v.frame_index for v in session.views]  # accepted while capturing, in that order
    result = session.finish()
    final = {v.frame_index for v in result.calibration.views}
    order = [i for i in live_order if i in final] + sorted(final - set(live_order))  # then the budget fill
    ours = Method("calibcoach", [dets[i] for i in order])
    ours.error_px = score(truth, result.calibration.camera, [v.image_points_px for v in result.calibration.views])
    ours.whole_px = whole_image_error(truth, result.calibration.camera)
    ours.outcome = result.verdict.grade + (" (BAD)" if result.verdict.trusted and is_bad(ours.error_px, ours.whole_px) else "")
    methods.append(ours)
    yardstick = [d.corners_px for d in usable]
    for method in methods:
        method.curve = efficiency_curve(truth, method.frames, yardstick)
    return methods


def efficiency_picture(name: str, methods: list[Method]) -> np.ndarray:
    from plots import line_chart  # bench/plots.py, beside this script

    series = {m.name: ([float(k) for k in m.curve[0]], [float(e) for e in m.curve[1]]) for m in methods if m.curve[0]}
    return line_chart(series, title=f"{name}: projection error vs truth by frames used",
                      x_label="frames used (in the order the method took them)",
                      y_label="error over the covered image, px", log_y=True, hline=EFFICIENCY_TARGET_PX)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", help="one session, e.g. webcam720_careful")
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--fps", type=float, default=8.0)
    parser.add_argument("--seed", type=int, default=7, help="another seed renders captures never seen before")
    args = parser.parse_args()
    accuracy = ["| session | method | error vs truth over the covered image, px | over the whole image, px | frames | outcome |",
                "|---|---|---|---|---|---|"]
    efficiency = [f"| session | method | frames to reach {EFFICIENCY_TARGET_PX} px | error after 20 frames, px |", "|---|---|---|---|"]
    results = ROOT / "results"
    results.mkdir(parents=True, exist_ok=True)
    for lens, style in SESSIONS:
        name = f"{lens}_{style}"
        if args.only and args.only != name:
            continue
        folder = rendered(lens, style, seconds=args.seconds, fps=args.fps, seed=args.seed)
        methods = evaluate(folder)
        for m in methods:
            line = f"| {lens} {style} | {m.name} | {m.error_px:.4f} | {m.whole_px:.3f} | {len(m.frames)} | {m.outcome} |"
            print(line, flush=True)
            accuracy.append(line)
            at20 = dict(zip(*m.curve, strict=True)).get(20, float("nan"))
            efficiency.append(f"| {lens} {style} | {m.name} | {frames_to_target(m.curve)} | {at20:.4f} |")
        cv2.imwrite(str(results / f"efficiency_{name}.png"), efficiency_picture(f"{lens} {style}", methods))
    text = (f"Captures: {args.seconds:g} s at {args.fps:g} fps, seed {args.seed}; BAD = accepted although more than "
            f"{BAD_PX} px wrong where the board was seen or {BAD_WHOLE_PX} px over the whole image. The plain recipe "
            "and the ROS-style selector accept whatever they solve; calibcoach accepts excellent, good and "
            "acceptable, and refuses insufficient.\n\n" + "\n".join(accuracy) + "\n\n## Frame efficiency\n\n" + "\n".join(efficiency) + "\n")
    out = results / "accuracy.md"
    out.write_text(text)
    print("\n".join(efficiency))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
