"""Corner error against the truth: OpenCV's corners, the masked refinement's, and the symmetry fit's.

For each cached render (bench/renders.py): every `--every`-th frame whose board moved at most
`--max-move` px between its neighbours (by the truth's poses) and shows at least 12 corners,
detected as the scan detects; its corners as OpenCV gives them, refined on the checker's edges
(coverage/corner_refine.py, the frame's own edge blur), and fitted to the pattern's point symmetry
from OpenCV's (coverage/corner_symmetry.py), as `frame_view` does for the final solve; each against
the truth's projection. Prints the RMS per axis of each. (The first runs in
bench/results/corner_symmetry.md fitted the symmetry from the masked corners, as the pipeline then did.)

    .venv/bin/python bench/corner_symmetry.py careful720_png_s101 dim720_png_s102 [--every 6] [--max-move 2]

The replays' error against the truth with the code as it stands: `bench/heldout.py --cached
--calibcoach-only`. bench/results/corner_symmetry.md quotes runs of both.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from renders import CACHE, detected_frames  # noqa: E402 - bench modules beside this one

from calibcoach.coverage.board import BoardSpec  # noqa: E402
from calibcoach.coverage.corner_refine import refine_on_checker_edges  # noqa: E402
from calibcoach.coverage.corner_symmetry import refine_by_symmetry  # noqa: E402
from calibcoach.coverage.sharpness import edge_blur  # noqa: E402
from calibcoach.drivers.recording import read_truth  # noqa: E402


def compare(name: str, *, every: int, max_move_px: float, limit: int) -> str:
    spec = BoardSpec()
    folder = CACHE / name
    truth = read_truth(folder)
    poses = {i: (r, t) for i, r, t in truth.poses}
    errors: dict[str, list[np.ndarray]] = {"OpenCV": [], "masked": [], "symmetry": []}
    frames = 0
    for index, grey, detection in detected_frames(name, every=every, min_corners=12):
        if index - 1 not in poses or index + 1 not in poses:
            continue
        board = detection.object_points_m.astype(np.float64)
        true = truth.camera.project(board, *poses[index])
        before = truth.camera.project(board, *poses[index - 1])
        after = truth.camera.project(board, *poses[index + 1])
        if np.abs(after - before).max() > max_move_px:
            continue
        corners = detection.corners_px.astype(np.float64)
        blur = edge_blur(grey, corners, detection.object_points_m).blur_px
        blur = blur if np.isfinite(blur) else None
        masked = refine_on_checker_edges(grey, corners, board, spec.square_mm / 1000.0, spec.marker_mm / 1000.0,
                                         blur_sigma_px=blur)
        fitted = refine_by_symmetry(grey, corners, board, spec, blur_sigma_px=blur)
        for key, found in (("OpenCV", corners), ("masked", masked), ("symmetry", fitted)):
            errors[key].append(found - true)
        frames += 1
        if frames >= limit:
            break
    if not frames:
        return f"| {name} | 0 | | | |"
    rms = {key: float(np.sqrt(np.mean(np.concatenate(v) ** 2))) for key, v in errors.items()}
    return f"| {name} | {frames} | {rms['OpenCV']:.4f} | {rms['masked']:.4f} | {rms['symmetry']:.4f} |"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("renders", nargs="+", help="cached render names, e.g. careful720_png_s101")
    parser.add_argument("--every", type=int, default=6, help="every n-th frame")
    parser.add_argument("--max-move", type=float, default=2.0, help="largest corner move between the frame's neighbours, px")
    parser.add_argument("--limit", type=int, default=40, help="frames per render")
    args = parser.parse_args()
    print("| render | frames | OpenCV, px per axis | masked | symmetry |")
    print("|---|---|---|---|---|")
    for name in args.renders:
        print(compare(name, every=args.every, max_move_px=args.max_move, limit=args.limit), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
