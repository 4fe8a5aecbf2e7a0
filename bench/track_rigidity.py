"""The held-board tracker's rigidity test: a fixed 0.5 px against one that allows for the corners' noise.

`CharucoBoardDetector.track` refuses a frame whose corners are not one rigid move of the frame
before's: a corner off the others' affine map by more than `TRACK_MAX_SPREAD_PX` (0.5 px), or, since
2026-12-05, by more than that *and* `TRACK_SPREAD_NOISE_SCALES` times the corners' own noise scale.
On dim footage the corners' noise alone put the worst corner past 0.5 px on ~40% of held frames,
each then detected in full on the scan's own thread.

For every cached render given (bench/renders.py), `run_replay` + `finish` with the defaults, once
with the fixed rule (`TRACK_SPREAD_NOISE_SCALES` = 0) and once with the noise allowed for; reported:
the error against the lens truth over the covered region (bench/accuracy.py's `score`), frames
tracked, seconds (in process), and the error ratio; then the geometric mean of the ratios per cell.
`--corners` also compares, on each render's held frames where only the new rule tracks, the tracked
corners (after the masked refinement the final solve takes) with the frame's own fresh detection,
both against the truth.

    .venv/bin/python bench/track_rigidity.py [--renders dim720_mjpg_s101 ...] [--corners] [--out track_rigidity]
    .venv/bin/python bench/track_rigidity.py --merge bench/results/a.json bench/results/b.json --out track_rigidity

Without --renders: every render in bench/cache. Writes bench/results/<out>.md and .json.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))

from heldout import cached_capture, calibcoach_run, geometric_mean_interval  # noqa: E402  (bench/heldout.py)
from renders import CACHE, cached_renders, capture_path  # noqa: E402

import calibcoach.coverage.detector as detector_module  # noqa: E402
from calibcoach.app.scan import board_shift_px  # noqa: E402
from calibcoach.app.session_finish import frame_view  # noqa: E402
from calibcoach.coverage.board import BoardSpec  # noqa: E402
from calibcoach.drivers.recording import read_truth  # noqa: E402
from calibcoach.drivers.replay import open_source  # noqa: E402

RULES = {"fixed 0.5 px": 0.0, "noise allowed for": detector_module.TRACK_SPREAD_NOISE_SCALES}


@contextmanager
def rule(name: str) -> Iterator[None]:
    """The tracker's rigidity test as `RULES[name]` inside the block, the module's own after it."""
    detector_module.TRACK_SPREAD_NOISE_SCALES = RULES[name]
    try:
        yield
    finally:
        detector_module.TRACK_SPREAD_NOISE_SCALES = RULES["noise allowed for"]


def replays(name: str) -> dict[str, dict]:
    path, truth, yardstick = cached_capture(name)
    rows = {}
    for name_of_rule in RULES:
        with rule(name_of_rule):
            run = calibcoach_run(path, truth.camera, yardstick, every_frame=False)
        rows[name_of_rule] = {"error_px": run.error_px, "frames": run.frames, "verdict": run.outcome,
                              "seconds": run.seconds, "tracked": run.extra.get("tracked")}
    return rows


def corner_errors(name: str) -> dict[str, float]:
    """Median corner error against the truth, tracked vs fresh, on held frames only the new rule tracks."""
    cell, seed = name.rsplit("_s", 1)
    truth = read_truth(CACHE / name)
    poses = {i: (r, t) for i, r, t in truth.poses}
    spec = BoardSpec()
    every_corner = spec.corner_points_m()
    detector = detector_module.CharucoBoardDetector(spec)

    def error(frame, found) -> float:  # the corners as the final solve takes them (masked refinement)
        refined = frame_view(frame, found, spec).as_refined().image_points_px
        true = truth.camera.project(every_corner[found.ids], *poses[frame.index])
        return float(np.median(np.linalg.norm(refined - true, axis=1)))

    tracked, fresh = [], []
    previous = None
    for frame in open_source(capture_path(cell, int(seed))):
        grey = frame.grey()
        found = detector.detect(grey)
        if previous is not None and min(previous.corner_count, found.corner_count) >= 6 and frame.index in poses \
                and board_shift_px(previous, found) <= 2.0:
            with rule("fixed 0.5 px"):
                before = detector.track(grey, previous)
            after = detector.track(grey, previous)
            if before is None and after is not None:
                tracked.append(error(frame, after))
                fresh.append(error(frame, found))
        previous = found
    return {"frames": len(tracked), "tracked_px": float(np.median(tracked)) if tracked else float("nan"),
            "fresh_px": float(np.median(fresh)) if fresh else float("nan")}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--renders", nargs="+", help="e.g. dim720_mjpg_s101 (default: every cached render)")
    parser.add_argument("--corners", action="store_true", help="also compare tracked and fresh corners against the truth")
    parser.add_argument("--out", default="track_rigidity")
    parser.add_argument("--merge", nargs="+", type=Path, help="only summarise these earlier .json results together")
    args = parser.parse_args()
    results: dict[str, dict] = {}
    if args.merge:  # renders measured in several runs (rendered at different times)
        for path in args.merge:
            results.update(json.loads(path.read_text()))
    else:
        for name in args.renders or [f"{cell}_s{seed}" for cell, seed in cached_renders()]:
            results[name] = replays(name)
            if args.corners:
                results[name]["corners"] = corner_errors(name)
            print(_row(name, results[name]), flush=True)
    lines = ["# The tracker's rigidity test: a fixed 0.5 px against one that allows for the corners' noise", "",
             "`bench/track_rigidity.py`: each render replayed with each rule (`run_replay` + `finish`, defaults); error "
             "against the lens truth over the covered region; seconds in process, with renders and other benches "
             "running beside them on this 2-core host (compare within a row only).", "",
             "| render | fixed 0.5 px: error, px | tracked | s | noise allowed for: error, px | tracked | s | ratio |",
             "|---|---|---|---|---|---|---|---|", *(_row(name, rows) for name, rows in results.items())]
    lines += ["", "| cell | renders | error ratio, geometric mean [95% bootstrap interval] | better / same / worse |",
              "|---|---|---|---|"]
    cells = sorted({n.rsplit("_s", 1)[0] for n in results})
    for label, chosen in [*((c, [c]) for c in cells), ("every dim render", [c for c in cells if c.startswith("dim")])]:
        ratios = np.array([r["noise allowed for"]["error_px"] / r["fixed 0.5 px"]["error_px"]
                           for n, r in results.items() if n.rsplit("_s", 1)[0] in chosen])
        if ratios.size:
            lines.append(f"| {label} | {ratios.size} | {geometric_mean_interval(ratios)} | {int((ratios < 0.999).sum())} / "
                         f"{int((np.abs(ratios - 1) <= 0.001).sum())} / {int((ratios > 1.001).sum())} |")
    with_corners = {name: rows["corners"] for name, rows in results.items() if "corners" in rows}
    if with_corners:
        lines += ["", "| render | frames only the new rule tracks | their tracked corners vs truth, px (median) | "
                  "their fresh detections' |", "|---|---|---|---|"]
        lines += [f"| {name} | {c['frames']} | {c['tracked_px']:.4f} | {c['fresh_px']:.4f} |" for name, c in with_corners.items()]
    (ROOT / "results" / f"{args.out}.md").write_text("\n".join(lines) + "\n")
    (ROOT / "results" / f"{args.out}.json").write_text(json.dumps(results, indent=1))
    print("\n".join(lines[len(results) + 6:]))
    return 0


def _row(name: str, rows: dict) -> str:
    a, b = rows["fixed 0.5 px"], rows["noise allowed for"]
    return (f"| {name} | {a['error_px']:.4f} ({a['verdict']}) | {a['tracked']} | {a['seconds']:.1f} | "
            f"{b['error_px']:.4f} ({b['verdict']}) | {b['tracked']} | {b['seconds']:.1f} | {b['error_px'] / a['error_px']:.2f} |")


if __name__ == "__main__":
    raise SystemExit(main())
