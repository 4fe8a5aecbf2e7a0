"""Where a replay's error against the truth comes from: its corners, or the poses it has.

For one cached render (bench/renders.py), runs `calibcoach calibrate`'s replay and scores it
against the lens truth over the covered region, with bench/heldout.py's yardstick (the detected
corners of every frame with >= 6), then solves the very
same final views (plain calibrateCamera, 5-term) three more ways:

- with their *true* corners plus independent noise of the detected corners' measured size
  (median over 5 draws): what these poses give a detector with no bias at all. When calibcoach
  lands near or under it, the capture's poses, not the corners or the selection, set the error;
- with the detected corners (the same solve without calibcoach's weighting and robust steps);
- with each view's mean corner error removed (how much is a per-view shift, e.g. smear).

    .venv/bin/python bench/error_sources.py dim720_mjpg 101 [102 ...]

Prints one block per render; bench/results/heldout.md ("Where the error comes from") has a run.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy import score, solve_plain  # noqa: E402 - bench modules beside this one
from heldout import detect_all  # noqa: E402
from renders import CACHE, capture_path  # noqa: E402

from calibcoach.app.replay import run_replay  # noqa: E402
from calibcoach.coverage.board import BoardSpec  # noqa: E402
from calibcoach.coverage.detector import Detection  # noqa: E402
from calibcoach.drivers.lens import CameraModel  # noqa: E402
from calibcoach.drivers.recording import read_truth  # noqa: E402
from calibcoach.drivers.replay import open_source  # noqa: E402

NOISE_DRAWS = 5


def _as_detection(corners_px: np.ndarray, like: Detection) -> Detection:
    return Detection(corners_px.astype(np.float32), like.ids, like.object_points_m, like.marker_ids)


def error_sources(cell: str, seed: int) -> str:
    folder = CACHE / f"{cell}_s{seed}"
    if not folder.is_dir():
        raise SystemExit(f"error_sources: {folder} is not rendered; run bench/heldout.py (or bench/renders.py) for it first")
    truth = read_truth(folder)
    lens = truth.camera
    poses = {i: (r, t) for i, r, t in truth.poses}
    every_frame, _seconds = detect_all(capture_path(cell, seed))
    covered = [d.corners_px for d in every_frame.values() if d.corner_count >= 6]  # bench/heldout.py's yardstick
    session, _stats = run_replay(open_source(capture_path(cell, seed)), BoardSpec())
    result = session.finish()
    views = result.calibration.views
    detected, true, shifts = [], [], []
    for v in views:
        det = Detection(v.image_points_px.astype(np.float32), v.ids, v.object_points_m.astype(np.float32), np.zeros(0, np.int32))
        r, t = poses[v.frame_index]
        true_px = lens.project(v.object_points_m, r, t)
        detected.append(det)
        true.append(_as_detection(true_px, det))
        shifts.append((v.image_points_px - true_px).mean(axis=0))
    errors = np.concatenate([d.corners_px - t.corners_px for d, t in zip(detected, true, strict=True)]).astype(np.float64)
    sigma = float(np.sqrt(np.mean(np.sum(errors**2, axis=1)) / 2.0))  # per axis
    start = CameraModel(lens.model, lens.camera_matrix, np.zeros(8), lens.image_size)
    rng = np.random.default_rng(0)
    noisy = sorted(score(lens, solve_plain([_as_detection(t.corners_px + rng.normal(0.0, sigma, t.corners_px.shape), t)
                                            for t in true], start), covered) for _ in range(NOISE_DRAWS))
    unshifted = [_as_detection(d.corners_px - s, d) for d, s in zip(detected, shifts, strict=True)]
    return "\n".join([
        f"{cell} s{seed}: calibcoach {score(lens, result.calibration.camera, covered):.3f} px "
        f"({len(views)} views, verdict {result.verdict.grade})",
        f"  detected corners vs truth: {np.sqrt(np.mean(np.sum(errors**2, axis=1))):.3f} px rms "
        f"(per-view mean shift {np.sqrt(np.mean(np.sum(np.array(shifts)**2, axis=1))):.3f} px rms)",
        f"  same views, true corners + iid noise {sigma:.3f} px/axis: {noisy[len(noisy) // 2]:.3f} px "
        f"(range {noisy[0]:.3f}-{noisy[-1]:.3f} over {NOISE_DRAWS} draws)",
        f"  same views, detected corners, plain solve: {score(lens, solve_plain(detected, start), covered):.3f} px",
        f"  same views, each view's mean shift removed: {score(lens, solve_plain(unshifted, start), covered):.3f} px",
    ])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cell", help="a bench/renders.py cell, e.g. dim720_mjpg")
    parser.add_argument("seeds", type=int, nargs="+")
    args = parser.parse_args()
    for seed in args.seeds:
        print(error_sources(args.cell, seed), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
