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

The masked refinement (coverage/corner_refine.py, which the final solve now uses) keeps a window
of half a square but gives zero weight to the pixels that lie, by a local quadratic image-to-board
map from the neighbouring corners, inside a marker's span (less twice the frame's edge blur):
the checker's four edges only, Gaussian-weighted, on the gradients at the pixels themselves.
For each render (or recording with truth.json): the replay's final views with OpenCV's corners
(`--corners opencv`), the same corners masked-refined in the same frames with a fixed 1.5 px
margin and with the blur-wide margin the pipeline uses, each solved plainly (calibrateCamera,
the truth's model family) and scored against the truth over the covered region (bench/heldout.py's
yardstick).

    .venv/bin/python bench/corner_masking.py [careful720_png:104 recordings/demo_webcam720_careful ...]

Writes bench/results/corner_masking.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))
from accuracy import score, solve_plain  # noqa: E402  (bench modules beside this one)
from heldout import detect_all  # noqa: E402
from renders import CACHE, cached_renders, capture_path  # noqa: E402

from calibcoach.app.replay import run_replay  # noqa: E402
from calibcoach.app.session_types import SessionSettings  # noqa: E402
from calibcoach.coverage.board import BoardSpec  # noqa: E402
from calibcoach.coverage.corner_refine import refine_on_checker_edges  # noqa: E402
from calibcoach.coverage.detector import Detection  # noqa: E402
from calibcoach.coverage.sharpness import edge_blur  # noqa: E402
from calibcoach.drivers.lens import CameraModel  # noqa: E402
from calibcoach.drivers.recording import read_truth  # noqa: E402
from calibcoach.drivers.replay import open_source  # noqa: E402


def compare(label: str, truth_folder: Path, capture: Path) -> str:
    spec = BoardSpec()
    truth = read_truth(truth_folder)
    lens = truth.camera
    poses = {i: (r, t) for i, r, t in truth.poses}
    every, _seconds = detect_all(capture)
    covered = [d.corners_px for d in every.values() if d.corner_count >= 6]  # bench/heldout.py's yardstick
    # the final views' frames and corners (the robust solve's outliers left out) as OpenCV detected them
    photos = open_source(capture).info.kind == "folder"  # as `calibcoach calibrate` sets it (app/commands.py)
    session, _stats = run_replay(open_source(capture), spec, SessionSettings(use_motion_gate=not photos, corners="opencv"))
    views = session.finish().calibration.views
    wanted = {v.frame_index for v in views}
    grey = {f.index: f.grey() for f in open_source(capture) if f.index in wanted}
    start = CameraModel(lens.model, lens.camera_matrix, np.zeros(8), lens.image_size)
    true_px = [lens.project(v.object_points_m, *poses[v.frame_index]) for v in views]
    square_m, marker_m = spec.square_mm / 1000.0, spec.marker_mm / 1000.0
    masked = [refine_on_checker_edges(grey[v.frame_index], v.image_points_px, v.object_points_m, square_m, marker_m)
              for v in views]
    blur_masked = [refine_on_checker_edges(grey[v.frame_index], v.image_points_px, v.object_points_m, square_m, marker_m,
                                           blur_sigma_px=edge_blur(grey[v.frame_index], v.image_points_px,
                                                                   v.object_points_m).blur_px)
                   for v in views]
    row = [label, str(len(views))]
    for corners in ([v.image_points_px for v in views], masked, blur_masked):
        errors = np.concatenate([c - t for c, t in zip(corners, true_px, strict=True)])
        solved = solve_plain([Detection(c.astype(np.float32), v.ids, v.object_points_m.astype(np.float32),
                                        np.zeros(0, np.int32)) for c, v in zip(corners, views, strict=True)], start)
        row += [f"{np.sqrt(np.mean(errors ** 2)):.4f}", f"{score(lens, solved, covered):.4f}"]
    return "| " + " | ".join(row) + " |"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("renders", nargs="*",
                        help="cell:seed, or a recording folder holding truth.json; default every render in bench/cache")
    args = parser.parse_args()
    todo = []
    for name in args.renders or [f"{c}:{s}" for c, s in cached_renders()]:
        if Path(name).is_dir():
            todo.append((Path(name).name, Path(name), Path(name)))
        else:
            cell, seed = name.split(":")
            todo.append((f"{cell} s{seed}", CACHE / f"{cell}_s{seed}", capture_path(cell, int(seed))))
    rows = ["| render | views | detected: corner error, px per coordinate | error vs truth, px | masked: corner error "
            "| error vs truth | blur-wide mask: corner error | error vs truth |",
            "|---|---|---|---|---|---|---|---|"]
    for label, truth_folder, capture in todo:
        rows.append(compare(label, truth_folder, capture))
        print(rows[-1], flush=True)
    text = "\n".join(rows)
    (ROOT / "results" / "corner_masking.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
