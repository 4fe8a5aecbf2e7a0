"""Blur limit: what lens blur does to ChArUco corners, and how well `edge_blur` reads it.

The selector refuses frames whose estimated edge blur exceeds `SelectorSettings.max_blur_px` (3 px)
or `max_blur_ratio` (2x) times the median of the frames kept so far. This bench measures the corner
error those limits correspond to, so that they rest on the error they cause rather than on one
recording: still frames (no motion, exposure 0) of a careful handheld path are rendered through
the webcam lens at increasing Gaussian lens blur, at normal light and in low light, several noise
seeds each, detected by calibcoach's detector and compared with the true corners. The default
board's markers stop decoding at ~1.5 px of blur at 720p and ~2.5 px at 1080p, before the limits
matter, so the default resolution is 4K (the same lens resized), where markers still decode at 4-5 px.

    .venv/bin/python bench/blur_limit.py [--seeds 2] [--poses 12] [--width 3840]

Prints, and writes to bench/results/blur_limit.md, per blur: the blur `edge_blur` measured
(median), the share of frames still giving >= 6 corners, the corners found per frame, and the
corner error against the truth (RMS over all corners, and the median of per-frame RMS).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector
from calibcoach.coverage.sharpness import edge_blur
from calibcoach.drivers.sim import LENSES, SimulatedCamera
from calibcoach.drivers.sim_paths import handheld_path

BLURS_PX = (0.6, 1.0, 2.0, 2.5, 3.0, 3.5, 4.0, 5.0, 6.0)
RESULTS = Path(__file__).resolve().parent / "results"


def still_poses(camera, spec: BoardSpec, count: int, seed: int):
    """`count` poses spread over a careful handheld path (each rendered still: exposure 0)."""
    path = handheld_path(camera, spec, "careful", seconds=60.0, fps=30.0, seed=seed)
    picks = np.linspace(0, len(path) - 1, count).astype(int)
    return [path[i] for i in picks]


def measure(blur_px: float, *, width: int, low_light: bool, seeds: int, poses_per_seed: int) -> dict[str, float]:
    spec = BoardSpec()
    camera = LENSES["webcam720"].resized((width, width * 9 // 16))
    detector = CharucoBoardDetector(spec)
    obj = spec.corner_points_m()
    measured, counts, frame_rms, all_err = [], [], [], []
    frames = usable = 0
    for seed in range(seeds):
        poses = still_poses(camera, spec, poses_per_seed, seed=200 + seed)
        sim = SimulatedCamera(camera, spec, poses, blur_sigma=blur_px, low_light=low_light, seed=300 + seed, exposure_s=0.0)
        for i, pose in enumerate(poses):
            grey = sim.render(i)
            detection = detector.detect(grey)
            frames += 1
            if detection.corner_count < 6:
                continue
            usable += 1
            truth = camera.project(obj[detection.ids], pose.rvec, pose.tvec)
            err = np.linalg.norm(detection.corners_px - truth, axis=1)
            all_err.append(err)
            frame_rms.append(float(np.sqrt(np.mean(err**2))))
            counts.append(detection.corner_count)
            measured.append(edge_blur(grey, detection.corners_px, detection.object_points_m).sharp_px)
    errors = np.concatenate(all_err) if all_err else np.zeros(0)
    return {
        "blur_px": blur_px, "measured_px": float(np.median(measured)) if measured else float("nan"),
        "usable": usable / max(frames, 1), "corners": float(np.median(counts)) if counts else 0.0,
        "rms_px": float(np.sqrt(np.mean(errors**2))) if errors.size else float("nan"),
        "frame_rms_px": float(np.median(frame_rms)) if frame_rms else float("nan"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--poses", type=int, default=12, help="still poses per seed")
    parser.add_argument("--width", type=int, default=3840, help="image width (16:9) the webcam lens is resized to")
    args = parser.parse_args()
    lines = ["| light | lens blur, px | edge_blur reads, px | frames with >= 6 corners | corners / frame | "
             "corner error RMS, px | per-frame RMS (median), px | error / at 0.6 px |", "|---|---|---|---|---|---|---|---|"]
    for low_light in (False, True):
        rows = [measure(b, width=args.width, low_light=low_light, seeds=args.seeds, poses_per_seed=args.poses) for b in BLURS_PX]
        sharp = rows[0]["rms_px"]
        for r in rows:
            line = (f"| {'low' if low_light else 'normal'} | {r['blur_px']:.1f} | {r['measured_px']:.2f} | {r['usable'] * 100:.0f}% | "
                    f"{r['corners']:.0f} | {r['rms_px']:.3f} | {r['frame_rms_px']:.3f} | {r['rms_px'] / sharp:.1f}x |")
            lines.append(line)
            print(line, flush=True)
    note = (f"\n{args.seeds} seeds x {args.poses} still poses of a careful path per row, the webcam lens at "
            f"{args.width}x{args.width * 9 // 16}, "
            "calibcoach's detector (CORNER_REFINE_SUBPIX), exposure 0 (no motion).\n")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "blur_limit.md").write_text("\n".join(lines) + "\n" + note)
    print(note)


if __name__ == "__main__":
    main()
