"""Whether a hold's frames share their corners' error: bias fixed to a pose, or independent noise.

A replay's final solve takes hundreds of frames from a dozen or two holds. Where the frames of one
hold share part of their corners' error (a bias that follows the board's pose there: blur,
perspective, compression of the same content), more frames of that hold do not average it out, and
only more holds would. Where the error is independent from frame to frame, the hold's frames do
average it, and the calibration's error is what the corner noise and the number of holds give.

For each render: the replay's final views (`run_replay` + `finish`, defaults), each corner's error
against the truth (detected - true projection), the views split into runs of consecutive frames
(a hold), each run's frames into odd and even. Per corner and run, the mean error of the odd frames
times that of the even frames estimates the variance of what the run's frames share (independent
noise averages to zero in the product); its mean over all corners and runs is the shared bias's
variance. Then the same views are solved plainly (calibrateCamera, bench/accuracy.py) with the true
corners plus each run's per-corner mean error only (what the hold shares, noise averaged in) and
plus the rest only (the frame-to-frame part), scored against the truth over the covered region.

    .venv/bin/python bench/hold_bias.py dim720_png_s103 [careful720_png_s101 ...]

Prints one line per render; bench/results/dim_noise.md quotes a run.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy import score, solve_plain  # noqa: E402 - bench modules beside this one
from heldout import cached_capture  # noqa: E402

from calibcoach.app.replay import run_replay  # noqa: E402
from calibcoach.app.solve.result import View  # noqa: E402
from calibcoach.coverage.board import BoardSpec  # noqa: E402
from calibcoach.coverage.detector import Detection  # noqa: E402
from calibcoach.drivers.lens import CameraModel  # noqa: E402
from calibcoach.drivers.replay import open_source  # noqa: E402

HOLD_GAP_FRAMES = 3  # frames further apart than this in the final solve belong to different holds
MIN_RUN = 6  # runs shorter than this give too few frames per half to average


def holds(views: list[View]) -> list[list[int]]:
    """Indices into `views` (sorted by frame) grouped into runs of nearby frames."""
    runs = [[0]]
    for i in range(1, len(views)):
        if views[i].frame_index - views[i - 1].frame_index <= HOLD_GAP_FRAMES:
            runs[-1].append(i)
        else:
            runs.append([i])
    return runs


def errors_by_corner(views: list[View], errors: list[np.ndarray], indices: list[int]) -> dict[int, list[np.ndarray]]:
    """Corner id -> its errors in the views at `indices`."""
    by_corner: dict[int, list[np.ndarray]] = {}
    for i in indices:
        for corner, error in zip(views[i].ids.reshape(-1), errors[i], strict=True):
            by_corner.setdefault(int(corner), []).append(error)
    return by_corner


def shared_bias_px(views: list[View], errors: list[np.ndarray], runs: list[list[int]]) -> float:
    """RMS per axis of the error a run's frames share beyond independent noise (odd x even halves)."""
    products = []
    for run in runs:
        if len(run) < MIN_RUN:
            continue
        odd, even = errors_by_corner(views, errors, run[0::2]), errors_by_corner(views, errors, run[1::2])
        for corner in set(odd) & set(even):
            products.append(np.mean(odd[corner], axis=0) * np.mean(even[corner], axis=0))
    return float(np.sqrt(max(float(np.mean(products)), 0.0))) if products else float("nan")


def split_by_hold(views: list[View], errors: list[np.ndarray], runs: list[list[int]]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Each view's error as (its run's per-corner mean, the rest)."""
    shared: list[np.ndarray] = [np.zeros(0)] * len(views)
    for run in runs:
        means = {corner: np.mean(e, axis=0) for corner, e in errors_by_corner(views, errors, run).items()}
        for i in run:
            shared[i] = np.array([means[int(c)] for c in views[i].ids.reshape(-1)])
    return shared, [e - s for e, s in zip(errors, shared, strict=True)]


def analyse(name: str) -> str:
    path, truth, covered = cached_capture(name)  # covered: bench/heldout.py's yardstick
    lens = truth.camera
    poses = {i: (r, t) for i, r, t in truth.poses}
    session, _stats = run_replay(open_source(path), BoardSpec())
    result = session.finish()
    views = sorted(result.calibration.views, key=lambda v: v.frame_index)
    true_px = [lens.project(v.object_points_m, *poses[v.frame_index]) for v in views]
    errors = [v.image_points_px - t for v, t in zip(views, true_px, strict=True)]
    runs = holds(views)
    shared, rest = split_by_hold(views, errors, runs)
    start = CameraModel(lens.model, lens.camera_matrix, np.zeros(8), lens.image_size)

    def solved_with(offsets: list[np.ndarray]) -> float:
        detections = [Detection((t + o).astype(np.float32), v.ids, v.object_points_m.astype(np.float32), np.zeros(0, np.int32))
                      for v, t, o in zip(views, true_px, offsets, strict=True)]
        return score(lens, solve_plain(detections, start), covered)

    corner_rms = float(np.sqrt(np.mean(np.concatenate(errors) ** 2)))
    sizes = sorted(len(r) for r in runs)
    return (f"| {name} | {score(lens, result.calibration.camera, covered):.4f} | {len(views)} in {len(runs)} runs "
            f"(median {sizes[len(sizes) // 2]}) | {corner_rms:.4f} | {shared_bias_px(views, errors, runs):.4f} | "
            f"{solved_with(errors):.4f} | {solved_with(shared):.4f} | {solved_with(rest):.4f} |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("renders", nargs="+", help="cached render names, e.g. dim720_png_s103")
    args = parser.parse_args()
    print("| render | calibcoach vs truth, px | final views | corner error, px per axis | shared within a hold "
          "beyond noise, px per axis | plain solve, detected corners | ... hold means only | ... the rest only |")
    print("|---|---|---|---|---|---|---|---|")
    for name in args.renders:
        print(analyse(name), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
