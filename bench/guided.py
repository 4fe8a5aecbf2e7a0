"""Does following the guidance pay? A simulated person in a closed loop with `calibcoach.Assistant`.

For each lens (70 deg webcam, 115 deg wide lens on the rational model, 150 deg fisheye) and each
strategy of `calibcoach.drivers.sim_person` (guided: does what the guidance says, with a person's
error; careful: its own thorough plan, no feedback; lazy: frontal and centred), over several seeds
and both a steady and a shaky hand: seconds and frames to the automatic stop (or "no stop" by
`--max-s`), frames accepted, E, the error against the lens truth over the region the board covered
and over the whole image, the verdict, and true error / E (how honest E is).

Every run drives the public API exactly as an embedding program would, at default settings.
A run renders ~10 frames per second of capture at 1x supersampling (~0.1 s per frame with
detection), so a 90 s session costs about a minute; `--jobs 2` uses both cores.

    .venv/bin/python bench/guided.py [--seeds 1 2 3 4 5] [--lenses webcam720 ...] [--strategies guided ...]
                                     [--hands steady shaky] [--fps 10] [--max-s 120] [--jobs 2]

Writes bench/results/guided.md (per-run rows, then median and worst per cell) and prints it.
"""

from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

import calibcoach
from calibcoach.app.solve.compare import projection_difference
from calibcoach.app.solve.uncertainty import covered_region_mask
from calibcoach.drivers.errors import CalibrationError
from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.sim import LENSES
from calibcoach.drivers.sim_person import HANDS, STRATEGIES, SimulatedPerson

ROOT = Path(__file__).resolve().parent
LENS_NAMES = ("webcam720", "wide720", "fisheye150")


@dataclass(frozen=True)
class Run:
    lens: str
    strategy: str
    hand: str
    seed: int
    stopped_s: float | None  # capture time of the automatic stop; None: no stop by max_s
    frames_fed: int
    accepted: int
    frames_used: int
    expected_error_px: float | None
    truth_covered_px: float | None
    truth_whole_px: float | None
    grade: str
    trusted: bool
    stop_reason: str
    wall_s: float
    repeats_unregistered: int  # most times in a row one target was shown at the end of a hold without a frame accepted


def truth_error(truth: CameraModel, result, views) -> tuple[float, float]:
    """RMS projection error against the truth over the covered region and over the whole image (px)."""
    estimate = CameraModel(result.model, result.camera_matrix, result.dist_coeffs, truth.image_size)
    mask = covered_region_mask(truth.image_size, [v.image_points_px for v in views], (32, 18))
    covered = projection_difference(truth, estimate, grid=(32, 18), mask=mask).rms_px
    whole = projection_difference(truth, estimate, grid=(32, 18)).rms_px
    return float(covered), float(whole)


def longest_unregistered_repeat(holds) -> int:
    """Holds in a row that followed the same target without anything accepted in between."""
    best = run = 0
    previous = None
    for target, accepted_during in holds:
        same = previous is not None and target is not None and np.allclose(target, previous)
        run = run + 1 if (same and not accepted_during) else (1 if target is not None else 0)
        best = max(best, run)
        previous = target
    return best


def run_one(lens: str, strategy: str, hand: str, seed: int, fps: float, max_s: float) -> Run:
    camera = LENSES[lens]
    board = calibcoach.BoardSpec()
    assistant = calibcoach.Assistant(board=board, image_size=camera.image_size, model="auto")
    person = SimulatedPerson(camera, board, strategy, seed=seed, fps=fps, hand=hand)
    start = time.perf_counter()
    run = person.run(assistant.feed, max_s=max_s)
    accepted_at = sorted(s.frame_index for s in run.steps if s.accepted)
    hold_log = []
    for hold in run.holds:
        asked = None if hold.asked is None else np.r_[hold.asked.centre_px, hold.asked.tilt_x_deg, hold.asked.tilt_y_deg,
                                                      hold.asked.distance_m]
        t0, t1 = hold.start_s * fps, hold.end_s * fps
        hold_log.append((asked, any(t0 - 12 <= i <= t1 for i in accepted_at)))
    try:
        result = assistant.finish()
    except CalibrationError as exc:
        return Run(lens, strategy, hand, seed, run.stopped_at_s, run.frames, len(accepted_at), 0, None, None, None,
                   f"failed: {exc}"[:60], False, assistant.session.stop_reason, time.perf_counter() - start,
                   longest_unregistered_repeat(hold_log))
    covered, whole = truth_error(camera, result, result.session.calibration.views)
    return Run(lens, strategy, hand, seed, run.stopped_at_s, run.frames, len(accepted_at),
               len(result.session.calibration.views), result.expected_error_px, covered, whole, result.verdict.grade,
               bool(result.verdict.trusted), assistant.session.stop_reason, time.perf_counter() - start,
               longest_unregistered_repeat(hold_log))


def _fmt(value, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def table(runs: list[Run]) -> str:
    lines = ["| lens | strategy | hand | seeds | stop s (median / worst) | stopped | frames kept | E px | truth covered px (median / worst) | truth whole px | truth / E | trusted |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    cells: dict[tuple[str, str, str], list[Run]] = {}
    for r in runs:
        cells.setdefault((r.lens, r.strategy, r.hand), []).append(r)
    for (lens, strategy, hand), rs in cells.items():
        stops = [r.stopped_s for r in rs if r.stopped_s is not None]
        truths = [r.truth_covered_px for r in rs if r.truth_covered_px is not None]
        wholes = [r.truth_whole_px for r in rs if r.truth_whole_px is not None]
        es = [r.expected_error_px for r in rs if r.expected_error_px is not None]
        ratio = [r.truth_covered_px / r.expected_error_px for r in rs if r.truth_covered_px and r.expected_error_px]
        lines.append(
            f"| {lens} | {strategy} | {hand} | {len(rs)} | "
            f"{_fmt(float(np.median(stops)), 0) if stops else '-'} / {_fmt(max(stops), 0) if len(stops) == len(rs) else 'no stop'} | "
            f"{len(stops)}/{len(rs)} | {int(np.median([r.accepted for r in rs]))} | {_fmt(float(np.median(es))) if es else '-'} | "
            f"{_fmt(float(np.median(truths))) if truths else '-'} / {_fmt(max(truths)) if truths else '-'} | "
            f"{_fmt(float(np.median(wholes))) if wholes else '-'} | "
            f"{_fmt(min(ratio), 2) if ratio else '-'}-{_fmt(max(ratio), 2) if ratio else '-'} | "
            f"{sum(r.trusted for r in rs)}/{len(rs)} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    parser.add_argument("--lenses", nargs="+", default=list(LENS_NAMES), choices=sorted(LENSES))
    parser.add_argument("--strategies", nargs="+", default=list(STRATEGIES), choices=STRATEGIES)
    parser.add_argument("--hands", nargs="+", default=["steady"], choices=sorted(HANDS))
    parser.add_argument("--fps", type=float, default=10.0)
    parser.add_argument("--max-s", type=float, default=120.0)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "guided.md")
    args = parser.parse_args()
    jobs = [(lens, strategy, hand, seed, args.fps, args.max_s) for lens in args.lenses for strategy in args.strategies
            for hand in args.hands for seed in args.seeds]
    runs: list[Run] = []
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        for run in pool.map(run_one, *zip(*jobs, strict=True)):
            runs.append(run)
            print(json.dumps(asdict(run)), flush=True)
    text = (f"# Closed-loop guidance bench\n\n`bench/guided.py --seeds {' '.join(map(str, args.seeds))} --fps {args.fps:g} "
            f"--max-s {args.max_s:g}`, {time.strftime('%Y-%m-%d')}\n\n{table(runs)}\n\n## Runs\n\n```\n"
            + "\n".join(json.dumps(asdict(r)) for r in runs) + "\n```\n")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(table(runs))


if __name__ == "__main__":
    main()
