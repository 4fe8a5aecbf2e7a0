"""Corner refinement's stopping accuracy: corner error against the truth, and what a tracked frame inherits.

OpenCV refines marker and ChArUco corners with `cornerSubPix`, stopping once a step is under
`cornerRefinementMinAccuracy` (0.1 px by default). Where a corner's iteration starts then shows in
where it stops. A full detection starts from the markers it found; a tracked frame
(`CharucoBoardDetector.track`, app/scan.py) from the previous frame's markers, moved. So a tracked
corner can inherit part of the previous frame's error. This measures, on rendered captures with
known poses (bench/renders.py cells, cached), for each pair of stopping accuracies (full detection /
tracking: OpenCV's 0.1 px for both, 0.01 for tracking only, 0.01 and 0.001 for both):

- the error of fully detected corners against the true corner positions, on held frames (the
  board moved < 2 px since the frame before: a hand's tremor, what tracking follows): rms and 95th percentile;
- the same for tracked corners (each held frame tracked from the full detection of the frame before),
  and how far they lie from the same frame's full detection (median, 95th percentile);
- the correlation of a corner's error in a frame with its error in the frame before, when the
  later frame is tracked from it, against the same when both are detected in full (errors that
  carry over down a chain of tracked frames do not average out in the solve).

    .venv/bin/python bench/corner_refinement.py [--cells careful720_png:101 shaky720_png:102 dim720_mjpg:101 ...]

Writes bench/results/corner_refinement.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))

from redetect import truth_px  # noqa: E402  (bench/redetect.py)
from renders import capture_path, render  # noqa: E402  (bench/renders.py)

from calibcoach.coverage import detector as D  # noqa: E402
from calibcoach.coverage.board import BoardSpec  # noqa: E402
from calibcoach.drivers.recording import read_truth  # noqa: E402
from calibcoach.drivers.replay import open_source  # noqa: E402

# (full detection's stopping accuracy, tracking's), px: OpenCV's default for both, a tighter
# stop for tracking only, and for both
SETTINGS = ((0.1, 0.1), (0.1, 0.01), (0.01, 0.01), (0.001, 0.001))
HELD_PX = 2.0  # the board moved less than this since the frame before (true corners)


def detector_with(accuracy_px: float) -> D.CharucoBoardDetector:
    """A detector that detects and tracks to `accuracy_px` (a settled spec: no print variant to find)."""
    return D.CharucoBoardDetector(BoardSpec().with_detected(legacy=False, inverted=False), corner_accuracy_px=accuracy_px)


def _corr(pairs: list[np.ndarray]) -> float:
    both = np.concatenate(pairs, axis=1)  # (2, N, 2): the same corners' errors in a frame and the frame before
    return float(np.corrcoef(both[0].ravel(), both[1].ravel())[0, 1])


def measure(cell: str, seed: int) -> list[dict]:
    folder = render(cell, seed)
    truth = read_truth(folder)
    poses = {i: (r, t) for i, r, t in truth.poses}
    accuracies = sorted({a for pair in SETTINGS for a in pair}, reverse=True)
    detectors = {acc: detector_with(acc) for acc in accuracies}
    keys = ("full", "full_same", "tracked", "gap", "pairs_tracked", "pairs_full")
    stats: dict[tuple[float, float], dict[str, list[np.ndarray]]] = {pair: {k: [] for k in keys} for pair in SETTINGS}
    previous: dict[float, tuple[int, D.Detection, np.ndarray] | None] = dict.fromkeys(accuracies)
    for frame in open_source(capture_path(cell, seed)):
        if frame.index not in poses:
            continue
        true_px, _inside = truth_px(truth.camera, *poses[frame.index])
        before = poses.get(frame.index - 1)
        held = before is not None and np.linalg.norm(true_px - truth_px(truth.camera, *before)[0], axis=1).max() < HELD_PX
        grey = frame.grey()
        found = {acc: detectors[acc].detect(grey) for acc in accuracies}
        for (detect_acc, track_acc), s in stats.items():
            full, last = found[detect_acc], previous[detect_acc]
            if not held or full.corner_count < 6:
                continue
            error = full.corners_px - true_px[full.ids]
            s["full"].append(error)
            if last is None or last[0] != frame.index - 1:
                continue
            _c, a, b = np.intersect1d(last[1].ids, full.ids, return_indices=True)
            s["pairs_full"].append(np.stack([last[2][a], error[b]]))
            # tracked from the frame before's full detection, refined to the tracking accuracy
            tracked = detectors[track_acc].track(grey, last[1])
            if tracked is None:
                continue
            t_error = tracked.corners_px - true_px[tracked.ids]
            _c, a, b = np.intersect1d(tracked.ids, full.ids, return_indices=True)
            s["tracked"].append(t_error[a])
            s["full_same"].append(error[b])
            s["gap"].append(np.linalg.norm(tracked.corners_px[a] - full.corners_px[b], axis=1))
            _c, a, b = np.intersect1d(last[1].ids, tracked.ids, return_indices=True)
            s["pairs_tracked"].append(np.stack([last[2][a], t_error[b]]))
        for acc in accuracies:
            f = found[acc]
            previous[acc] = (frame.index, f, f.corners_px - true_px[f.ids]) if f.corner_count >= 6 else None
    rows = []
    for (detect_acc, track_acc), s in stats.items():
        def rms(key: str, s: dict = s) -> float:
            return float(np.sqrt(np.mean(np.sum(np.concatenate(s[key]) ** 2, axis=1))))

        full_n = np.linalg.norm(np.concatenate(s["full"]), axis=1)
        gap = np.concatenate(s["gap"])
        rows.append({"cell": f"{cell} s{seed}", "detect": detect_acc, "track": track_acc, "full_n": full_n.size,
                     "full_rms": rms("full"), "full_p95": float(np.percentile(full_n, 95)),
                     "tracked_n": int(gap.size), "tracked_rms": rms("tracked"), "full_same_rms": rms("full_same"),
                     "gap_median": float(np.median(gap)), "gap_p95": float(np.percentile(gap, 95)),
                     "corr_tracked": _corr(s["pairs_tracked"]), "corr_full": _corr(s["pairs_full"])})
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", nargs="+",
                        default=["careful720_png:101", "shaky720_png:102", "dim720_mjpg:101", "fisheye150_png:101"],
                        help="CELL:SEED of bench/renders.py")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    lines = ["| capture | stop accuracy, px: detection / tracking | held-frame corners | full detection vs truth: rms | p95 "
             "| tracked corners | tracked vs truth: rms | the same corners fully detected: rms | tracked - full: median | p95 "
             "| error correlation with the frame before: into a tracked frame | between full detections |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for item in args.cells:
        cell, seed = item.split(":")
        for r in measure(cell, int(seed)):
            line = (f"| {r['cell']} | {r['detect']:g} / {r['track']:g} | {r['full_n']} | {r['full_rms']:.4f} | "
                    f"{r['full_p95']:.4f} | {r['tracked_n']} | {r['tracked_rms']:.4f} | {r['full_same_rms']:.4f} | "
                    f"{r['gap_median']:.4f} | {r['gap_p95']:.4f} | {r['corr_tracked']:.3f} | {r['corr_full']:.3f} |")
            print(line, flush=True)
            lines.append(line)
    (ROOT / "results" / "corner_refinement.md").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
