"""Where the careful renders' error comes from, and a corner refinement that removes most of it.

bench/error_sources.py found the final views of careful renders s104/s105 calibrating to 0.07-0.09
px against the truth where the same views with unbiased noise of the same size give 0.02-0.03.
Decomposing each view's corner errors (detected - true) over the board:

- shuffling each view's errors among its corners, or flipping each view's errors' sign at random,
  brings the error down to the unbiased level: the harm is in a spatial pattern within each view
  whose sign is consistent across views (neither fixed to the board nor to the image: both
  residual-pattern ratios ~1, bench/residual_patterns.py);
- a quadratic in board coordinates fitted per view (0.015 px rms) carries all of it (solved
  alone: 0.071 px; the errors without it: 0.004 px on s104);
- smaller cornerSubPix windows remove it but multiply the noise (dim and messy renders 2-8x
  worse): OpenCV's ChArUco window stops 2 px short of the nearest *marker corner*, so it takes
  in the edges of the markers that sit in the two white squares; their gradients pull the corner.

The masked refinement here keeps a window of half a square but gives zero weight to the pixels
that lie, by the local board-to-image map from the neighbouring corners, inside a marker's span
(less a 1.5 px blur margin): the checker's four edges only, Gaussian-weighted, iterated as
cornerSubPix does. For each cached render: the replay's final views, their corners as detected
and masked-refined in the same frames, each solved plainly (calibrateCamera, the truth's model
family) and scored against the truth over the covered region (bench/heldout.py's yardstick).

    .venv/bin/python bench/corner_masking.py [careful720_png:104 dim720_mjpg:101 ...]

Writes bench/results/corner_masking.md. The refinement is a per-corner Python loop here (~70 ms a
720p frame of 70 corners); vectorized over a frame's corners (one remap per iteration for all the
windows) it took ~20 ms, still too much for the ~400 frames a replay judges usable, so it is not
yet in calibcoach's pipeline: sampling only the unmasked pixels (~40% of each window), fewer
iterations and the affine from the grid neighbours should bring it to a few ms.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))
from accuracy import score, solve_plain  # noqa: E402  (bench modules beside this one)
from heldout import detect_all  # noqa: E402
from renders import CACHE, cached_renders, capture_path  # noqa: E402

from calibcoach.app.replay import run_replay  # noqa: E402
from calibcoach.coverage.board import BoardSpec  # noqa: E402
from calibcoach.coverage.detector import Detection  # noqa: E402
from calibcoach.drivers.lens import CameraModel  # noqa: E402
from calibcoach.drivers.recording import read_truth  # noqa: E402
from calibcoach.drivers.replay import open_source  # noqa: E402

BLUR_MARGIN_PX = 1.5  # pixels this close to a marker's span are left out too (the edge's blur reaches them)
MAX_HALF_PX = 12  # window half-size cap; half a square below it
ITERATIONS = 8
STOP_PX = 0.001


def masked_refine(grey: np.ndarray, corners_px: np.ndarray, board_xy_m: np.ndarray, square_m: float,
                  marker_m: float) -> np.ndarray:
    """Corners refined on the checker's edges alone: (N, 2) px, from (N, 2) detected corners.

    Each corner's window (half a square, Gaussian-weighted) leaves out the pixels that the local
    board-to-image map (an affine fitted to the corners within 1.6 squares) puts inside the span
    of the markers in the two white squares, so only the four checker edges meeting at the corner
    pull it. A corner without two non-collinear neighbours, or that would move by 3 px or more,
    keeps its detected position.
    """
    image = grey.astype(np.float32)
    gx = cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    margin = (square_m - marker_m) / 2.0 / square_m  # the white border around a marker, in squares
    out = corners_px.astype(np.float64).copy()
    apart = np.linalg.norm(board_xy_m[:, None] - board_xy_m[None], axis=2)
    for k in range(len(out)):
        near = np.flatnonzero((apart[k] > 0) & (apart[k] < 1.6 * square_m))
        if near.size < 2:
            continue
        A, *_ = np.linalg.lstsq((board_xy_m[near] - board_xy_m[k]) / square_m, corners_px[near] - corners_px[k], rcond=None)
        if abs(np.linalg.det(A)) < 1e-6:
            continue
        square_px = float(np.sqrt(abs(np.linalg.det(A))))
        half = int(np.clip(0.5 * square_px, 2, MAX_HALF_PX))
        ys, xs = np.mgrid[-half:half + 1, -half:half + 1].astype(np.float64)
        offsets = np.stack([xs.ravel(), ys.ravel()], axis=1)
        uv = offsets @ np.linalg.inv(A)  # the window's pixels in squares from the corner
        edge = margin - BLUR_MARGIN_PX / square_px
        in_marker = (np.abs(uv[:, 0]) > edge) & (np.abs(uv[:, 1]) > edge)
        weight = np.exp(-(offsets ** 2).sum(axis=1) / (2 * (half / 2.0) ** 2)) * ~in_marker
        q = out[k].copy()
        for _ in range(ITERATIONS):
            size = (2 * half + 1, 2 * half + 1)
            sx = cv2.getRectSubPix(gx, size, (float(q[0]), float(q[1]))).ravel().astype(np.float64)
            sy = cv2.getRectSubPix(gy, size, (float(q[0]), float(q[1]))).ravel().astype(np.float64)
            px, py = q[0] + offsets[:, 0], q[1] + offsets[:, 1]
            a, b, c = (weight * sx * sx).sum(), (weight * sx * sy).sum(), (weight * sy * sy).sum()
            r1 = (weight * (sx * sx * px + sx * sy * py)).sum()
            r2 = (weight * (sx * sy * px + sy * sy * py)).sum()
            det = a * c - b * b
            if abs(det) < 1e-9:
                break
            step = np.array([(c * r1 - b * r2) / det, (a * r2 - b * r1) / det])
            moved = float(np.linalg.norm(step - q))
            q = step
            if moved < STOP_PX:
                break
        if np.linalg.norm(q - corners_px[k]) < 3.0:
            out[k] = q
    return out


def compare(cell: str, seed: int) -> str:
    spec = BoardSpec()
    truth = read_truth(CACHE / f"{cell}_s{seed}")
    lens = truth.camera
    poses = {i: (r, t) for i, r, t in truth.poses}
    every, _seconds = detect_all(capture_path(cell, seed))
    covered = [d.corners_px for d in every.values() if d.corner_count >= 6]  # bench/heldout.py's yardstick
    session, _stats = run_replay(open_source(capture_path(cell, seed)), spec)
    views = session.finish().calibration.views
    wanted = {v.frame_index for v in views}
    grey = {f.index: f.grey() for f in open_source(capture_path(cell, seed)) if f.index in wanted}
    start = CameraModel(lens.model, lens.camera_matrix, np.zeros(8), lens.image_size)
    true_px = [lens.project(v.object_points_m, *poses[v.frame_index]) for v in views]
    masked = [masked_refine(grey[v.frame_index], v.image_points_px, v.object_points_m[:, :2], spec.square_mm / 1000.0,
                            spec.marker_mm / 1000.0) for v in views]
    row = [f"{cell} s{seed}", str(len(views))]
    for corners in ([v.image_points_px for v in views], masked):
        errors = np.concatenate([c - t for c, t in zip(corners, true_px, strict=True)])
        solved = solve_plain([Detection(c.astype(np.float32), v.ids, v.object_points_m.astype(np.float32),
                                        np.zeros(0, np.int32)) for c, v in zip(corners, views, strict=True)], start)
        row += [f"{np.sqrt(np.mean(errors ** 2)):.4f}", f"{score(lens, solved, covered):.4f}"]
    return "| " + " | ".join(row) + " |"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("renders", nargs="*", help="cell:seed; default every render in bench/cache")
    args = parser.parse_args()
    todo = [(r.split(":")[0], int(r.split(":")[1])) for r in args.renders] or cached_renders()
    rows = ["| render | views | detected: corner error, px per coordinate | error vs truth, px | masked: corner error | error vs truth |",
            "|---|---|---|---|---|---|"]
    for cell, seed in todo:
        rows.append(compare(cell, seed))
        print(rows[-1], flush=True)
    text = "\n".join(rows)
    (ROOT / "results" / "corner_masking.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
