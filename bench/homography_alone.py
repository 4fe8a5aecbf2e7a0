"""The corners the symmetry fit used to leave as OpenCV gave them, fitted through the homography alone.

A corner's samples are placed by the frame's homography bent by a quadratic through its grid
neighbours; where four of them are not in general position (the edge of what was detected: the
image's border, markers a dim or smeared frame lost) the quadratic is undetermined, and those
corners were left as OpenCV gave them. Now they are fitted on the homography alone
(coverage/corner_symmetry.py). For each cached render (bench/renders.py), every `--every`-th frame
with at least 8 corners: the corners fitted either way, and those only the homography-alone map
fits, before (OpenCV's) and after, each against the truth's projection through the frame's pose
solved under the true lens on the corners fitted either way (so a smear's or the tremor's shift
of the whole board within the exposure does not count). Prints the RMS per axis of each.

    .venv/bin/python bench/homography_alone.py dim720_png_s104 careful720_png_s101 [--every 4]

The replays' error against the truth before and after: `bench/heldout.py --cached
--calibcoach-only` on the code of each. bench/results/homography_alone.md quotes runs of both.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from renders import CACHE, detected_frames  # noqa: E402 - bench modules beside this one

from calibcoach.coverage.board import BoardSpec  # noqa: E402
from calibcoach.coverage.corner_refine import board_grid, grid_neighbours, in_general_position  # noqa: E402
from calibcoach.coverage.corner_symmetry import refine_by_symmetry  # noqa: E402
from calibcoach.coverage.sharpness import edge_blur  # noqa: E402
from calibcoach.drivers.recording import read_truth  # noqa: E402


def compare(name: str, *, every: int) -> str:
    spec = BoardSpec()
    folder = CACHE / name
    truth = read_truth(folder)
    K, D = truth.camera.camera_matrix, np.asarray(truth.camera.dist_coeffs, np.float64)
    before, after, either, frames = [], [], [], 0
    for _index, grey, detection in detected_frames(name, every=every, min_corners=8):
        corners = detection.corners_px.astype(np.float64)
        board = detection.object_points_m.astype(np.float64)
        blur = edge_blur(grey, corners, board).blur_px
        blur = blur if np.isfinite(blur) else None
        grid = board_grid(board, spec.square_mm / 1000.0)
        determined = in_general_position(grid_neighbours(grid) >= 0)
        fitted = refine_by_symmetry(grey, corners, board, spec, blur_sigma_px=blur)
        moved = np.any(fitted != corners, axis=1)
        both, only_now = moved & determined, moved & ~determined
        if both.sum() < 6 or not only_now.any():
            continue
        ok, rvec, tvec = cv2.solvePnP(board[both], fitted[both].reshape(-1, 1, 2), K, D)
        if not ok:
            continue
        true = cv2.projectPoints(board, rvec, tvec, K, D)[0].reshape(-1, 2)
        before.append(corners[only_now] - true[only_now])
        after.append(fitted[only_now] - true[only_now])
        either.append(fitted[both] - true[both])
        frames += 1
    if not frames:
        return f"| {name} | 0 | - | - | - | - |"

    def rms(parts: list[np.ndarray]) -> float:
        return float(np.sqrt(np.mean(np.concatenate(parts) ** 2)))

    n_now, n_both = sum(len(p) for p in before), sum(len(p) for p in either)
    return (f"| {name} | {frames} | {n_now} ({n_now / (n_now + n_both):.0%}) | {rms(before):.4f} | {rms(after):.4f} | "
            f"{rms(either):.4f} |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("renders", nargs="+", help="cached render names, e.g. dim720_png_s104")
    parser.add_argument("--every", type=int, default=4, help="every n-th frame")
    args = parser.parse_args()
    print("| render | frames | corners fitted only on the homography | their error, OpenCV's | fitted | corners fitted either way |")
    print("|---|---|---|---|---|---|")
    for name in args.renders:
        print(compare(name, every=args.every), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
