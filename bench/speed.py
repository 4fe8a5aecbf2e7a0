"""Speed: per-frame cost by stage and resolution, solve time against frame count, replay throughput.

1. Per frame at 720p, 1080p and 4K, on a few rendered frames of a careful handheld capture:
   PNG decode, bare OpenCV `detectBoard` (default threads and one thread), calibcoach detection,
   the session step and Rerun logging (to a file only, as replay and as live log), each frame
   timed on its own after a warm-up frame; median and p90, and the frame rates they allow.
2. `solve()` time against the number of views for the pinhole, rational and fisheye models, on the
   detections of the cached careful 720p capture, and `finish()` after a whole replay of it.
3. Replay throughput (frames/s) of that recording, and of an image folder given with --folder.

Rendered frames are cached as recordings in bench/cache/ (git-ignored) and reused. Usage:

    .venv/bin/python bench/speed.py [--folder IMAGES] [--skip-solve]

Writes bench/results/speed.md, speed_per_frame.png and solve_time.png, and prints the tables.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from collections.abc import Callable
from datetime import date
from pathlib import Path

import cv2
import numpy as np
from accuracy import render_recording
from plots import grouped_bars, line_chart, save

from calibcoach.app.replay import run_replay
from calibcoach.app.session import CalibrationSession, FrameOutcome, SessionSettings
from calibcoach.app.solve.calibrate import solve
from calibcoach.app.solve.result import View
from calibcoach.app.viewer import Viewer
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector, Detection
from calibcoach.drivers.base import Frame
from calibcoach.drivers.errors import CalibrationError
from calibcoach.drivers.image_files import decode_image
from calibcoach.drivers.replay import open_source
from calibcoach.drivers.sim import LENSES

ROOT = Path(__file__).resolve().parent  # a bench script may find its own folder; the package never does
RESULTS = ROOT / "results"
DEFAULT_THREADS = cv2.getNumThreads()  # read before any CalibrationSession sets it to 1
CORES = 2  # replay's detection workers; the machine this was written for has 2
# (name, lens, frames): few frames, since rendering costs ~0.4 s per 720p frame and ~9x that at 4K
RESOLUTIONS = [
    ("720p", LENSES["webcam720"], 10),
    ("1080p", LENSES["webcam1080"], 10),
    ("4K", LENSES["webcam1080"].resized((3840, 2160)), 6),
]
# Two frames a second spread the few frames over moves and dwells: the board is found in about 7 of
# 10 (the others are blurred by a move), as in a real careful capture.
RENDER_FPS = 2.0
SOLVE_CAPTURE = "webcam720_careful_30s_8fps"
SOLVE_COUNTS = (10, 20, 40, 60, 100)
SOLVE_MODELS = ("pinhole", "rational", "fisheye")
LIVE_FPS = 30.0
LOG = "Rerun log_frame"
LOG_LIVE = "Rerun log_frame, no image (live)"
TOTAL = "total (detect+step+log_frame)"
PLOT_LEFT_OUT = ("Rerun live preview (capture thread)", LOG_LIVE)  # in the table; the chart stays readable
ROUNDS = 3  # per-frame timings are repeated and the fastest kept: the machine may be shared


# --- rendering ------------------------------------------------------------------------------------
def rendered_speed_capture(name: str, camera, frames: int) -> Path:
    """A cached recording of `frames` frames of a careful handheld path, two a second."""
    folder = ROOT / "cache" / f"speed_{name}_{RENDER_FPS:g}fps"
    if (folder / "session.json").exists() and len(list((folder / "frames").glob("*.png"))) >= frames:
        return folder
    render_recording(folder, camera, lens_name=f"speed_{name}", style="careful", seconds=frames / RENDER_FPS,
                     fps=RENDER_FPS, seed=7)
    return folder


def solve_capture() -> Path:
    folder = ROOT / "cache" / SOLVE_CAPTURE
    if not (folder / "session.json").exists():
        from accuracy import rendered  # only needed when the cache is cold

        folder = rendered("webcam720", "careful", seconds=30, fps=8)
    return folder


# --- timing helpers -------------------------------------------------------------------------------
def ms_of(call: Callable[[], object]) -> tuple[object, float]:
    start = time.perf_counter()
    result = call()
    return result, (time.perf_counter() - start) * 1e3


def timed_each(items: list, call: Callable[[object], object]) -> list[float]:
    """ms of `call(item)` for each item, after one untimed warm-up call on the first."""
    call(items[0])
    return [ms_of(lambda item=item: call(item))[1] for item in items]


def median_p90(values: list[float]) -> tuple[float, float]:
    return float(np.median(values)), float(np.percentile(values, 90))


# --- 1. per-frame cost ----------------------------------------------------------------------------
def bare_detector(spec: BoardSpec) -> cv2.aruco.CharucoDetector:
    """What a user would write with OpenCV alone."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return cv2.aruco.CharucoDetector(spec.cv_board(), cv2.aruco.CharucoParameters(), params)


def session_step_times(frames: list[Frame], detections: list[Detection]) -> tuple[list[float], list[FrameOutcome]]:
    """ms of `process` per frame as replay drives it (one frame of lookahead); the first is a warm-up."""
    session = CalibrationSession(BoardSpec(), frames[0].image_size, SessionSettings())
    times, outcomes = [], []
    for i, (frame, detection) in enumerate(zip(frames, detections, strict=True)):
        following = (detections[i + 1], frames[i + 1].timestamp_ns) if i + 1 < len(frames) else None
        outcome, ms = ms_of(lambda f=frame, d=detection, n=following: session.process(f, d, following=n))
        times.append(ms)
        outcomes.append(outcome)
    return times[1:], outcomes


def logging_times(frames: list[Frame], outcomes: list[FrameOutcome]) -> dict[str, list[float]]:
    """ms per frame of Rerun logging, saving to a file only (mode "none"); the first frame is a warm-up.

    Replay logs whole frames (`log_frame`); live logs the image on the capture thread (`log_preview`)
    and the overlays on the processing thread (`log_frame(image=False)`), so both ways are timed.
    """
    pairs = list(zip(outcomes, frames, strict=True))
    with tempfile.TemporaryDirectory() as out:
        replay_viewer = Viewer.open("none", out_dir=Path(out) / "replay", application_id="calibcoach_bench")
        live_viewer = Viewer.open("none", out_dir=Path(out) / "live", application_id="calibcoach_bench")
        try:
            times = {
                LOG: [ms_of(lambda o=o, f=f: replay_viewer.log_frame(o, f))[1] for o, f in pairs],
                "Rerun live preview (capture thread)": [ms_of(lambda f=f: live_viewer.log_preview(f))[1] for f in frames],
                LOG_LIVE: [ms_of(lambda o=o, f=f: live_viewer.log_frame(o, f, image=False))[1] for o, f in pairs],
            }
        finally:
            replay_viewer.close()
            live_viewer.close()
    return {k: v[1:] for k, v in times.items()}


def stage_times_once(folder: Path) -> tuple[dict[str, list[float]], int]:
    """ms per frame for each stage on the frames of one cached recording, and the frames with a board."""
    spec = BoardSpec()
    pngs = [np.fromfile(p, np.uint8) for p in sorted((folder / "frames").glob("*.png"))]
    frames = list(open_source(folder))
    greys = [f.grey() for f in frames]
    stages = {"decode": timed_each(pngs, lambda b: decode_image(b, fast_png=True))}  # as a replay decodes them
    bare = bare_detector(spec)
    cv2.setNumThreads(DEFAULT_THREADS)
    stages[f"OpenCV detect, {DEFAULT_THREADS} threads"] = timed_each(greys, bare.detectBoard)
    cv2.setNumThreads(1)  # calibcoach's own setting, kept for the stages below (the session sets it too)
    stages["OpenCV detect, 1 thread"] = timed_each(greys, bare.detectBoard)
    detector = CharucoBoardDetector(spec)  # the warm-up frame also settles the print's variant
    stages["calibcoach detect"] = timed_each(greys, detector.detect)[1:]  # aligned with the two below
    detections = [detector.detect(g) for g in greys]
    stages["session step"], outcomes = session_step_times(frames, detections)
    stages.update(logging_times(frames, outcomes))
    cv2.setNumThreads(DEFAULT_THREADS)
    return stages, sum(d.corner_count >= 6 for d in detections)


def stage_times(folder: Path) -> tuple[dict[str, list[float]], int]:
    """Per frame and stage, the fastest of ROUNDS rounds: the cost without another process's interference."""
    rounds = [stage_times_once(folder) for _ in range(ROUNDS)]
    stages = {k: np.min([r[0][k] for r in rounds], axis=0).tolist() for k in rounds[0][0]}
    stages[TOTAL] = [c + d + e for c, d, e in zip(
        stages["calibcoach detect"], stages["session step"], stages[LOG], strict=True)]
    return stages, rounds[0][1]


def throughput(stages: dict[str, list[float]]) -> tuple[float, float, float]:
    """Frames/s: all on one core; replay on CORES cores; the live processing thread.

    Replay detects on worker threads while one thread steps the session and another logs, so the
    slower of those two threads or the cores' total work binds. Live detects, steps and logs the
    overlays on one thread, detection on OpenCV's two threads (the capture thread logs the image).
    """
    median = {k: float(np.median(v)) for k, v in stages.items()}
    one = 1e3 / median[TOTAL]
    replay = min(1e3 / median["session step"], 1e3 / median[LOG], CORES * one)
    # live detection runs with OpenCV's own threads (app/live.py detect_on_all_cores): bit-identical
    # corners, the time of the bare 2-thread detectBoard
    live = 1e3 / (median[f"OpenCV detect, {DEFAULT_THREADS} threads"] + median["session step"] + median[LOG_LIVE])
    return one, replay, live


def per_frame_section() -> tuple[list[str], dict[str, dict[str, list[float]]]]:
    results, found = {}, {}
    for name, camera, count in RESOLUTIONS:
        results[name], found[name] = stage_times(rendered_speed_capture(name, camera, count))
        print(f"measured {name}")
    lines = ["| resolution | stage | median ms | p90 ms |", "|---|---|---|---|"]
    for name, stages in results.items():
        for stage, ms in stages.items():
            lines.append(f"| {name} | {stage} | {median_p90(ms)[0]:.1f} | {median_p90(ms)[1]:.1f} |")
    lines += ["", f"| resolution | board found | detect+step+log_frame median ms | 1 core, frames/s | {CORES} cores "
              f"(replay), frames/s | live processing thread, frames/s | live keeps {LIVE_FPS:g} fps? |",
              "|---|---|---|---|---|---|---|"]
    for (name, stages), (_, _, count) in zip(results.items(), RESOLUTIONS, strict=True):
        one, replay, live = throughput(stages)
        lines.append(f"| {name} | {found[name]} of {count} | {np.median(stages[TOTAL]):.1f} "
                     f"| {one:.1f} | {replay:.1f} | {live:.1f} | {live_verdict(live)} |")
    return lines, results


def live_verdict(fps: float) -> str:
    # timings on a shared machine move by ~10%, so a rate that close to the target is called borderline
    if fps >= 1.1 * LIVE_FPS:
        return "yes"
    if fps >= 0.9 * LIVE_FPS:
        return "borderline"
    return f"no: ~{fps:.0f} of {LIVE_FPS:g} frames/s processed, the rest dropped"


def per_frame_plot(results: dict[str, dict[str, list[float]]]) -> None:
    names = [s for s in next(iter(results.values())) if s not in PLOT_LEFT_OUT]
    series = {s: [float(np.median(results[r][s])) for r in results] for s in names}
    img = grouped_bars(list(results), series, title="Per-frame cost by stage", y_label="ms per frame (median)",
                       subtitle="rendered careful handheld frames; calibcoach stages on 1 OpenCV thread",
                       size=(1400, 640))
    save(img, RESULTS / "speed_per_frame.png")


# --- 2. solve time --------------------------------------------------------------------------------
def capture_views(folder: Path) -> tuple[list[View], tuple[int, int]]:
    """Views of every frame with >= 6 corners, built as the session builds them."""
    source = open_source(folder)
    detector = CharucoBoardDetector(BoardSpec.from_dict(dict(source.info.board)))
    views, size = [], None
    for frame in source:
        size = frame.image_size
        d = detector.detect(frame.grey())
        if d.corner_count >= 6:
            views.append(View(frame.index, frame.name, d.ids.copy(), d.corners_px.astype(np.float64),
                              d.object_points_m.astype(np.float64)))
    return views, size


def solve_ms(views: list[View], size: tuple[int, int], model: str, runs: int = 3) -> float:
    try:
        return float(np.median([ms_of(lambda: solve(views, size, model))[1] for _ in range(runs)]))
    except CalibrationError:
        return float("nan")


def solve_section(folder: Path) -> tuple[list[str], dict[str, tuple[list[float], list[float]]]]:
    views, size = capture_views(folder)
    cv2.setNumThreads(1)  # as in a session
    counts = [n for n in SOLVE_COUNTS if n <= len(views)]
    # n views spread evenly over the capture, as a session's selection is; the first n would be a
    # few seconds of near-identical frames
    picks = {n: [views[i] for i in np.linspace(0, len(views) - 1, n).round().astype(int)] for n in counts}
    curves = {m: (list(map(float, counts)), [solve_ms(picks[n], size, m) / 1e3 for n in counts]) for m in SOLVE_MODELS}
    cv2.setNumThreads(DEFAULT_THREADS)
    lines = [f"{len(views)} frames with >= 6 corners in {folder.name}; `solve()` median of 3, seconds:", "",
             "| views | " + " | ".join(SOLVE_MODELS) + " |", "|---|" + "---|" * len(SOLVE_MODELS)]
    for i, n in enumerate(counts):
        lines.append(f"| {n} | " + " | ".join(f"{curves[m][1][i]:.3f}" for m in SOLVE_MODELS) + " |")
    return lines, curves


def solve_plot(curves: dict[str, tuple[list[float], list[float]]]) -> None:
    ys = [y for _, v in curves.values() for y in v if np.isfinite(y) and y > 0]
    log_y = bool(ys) and max(ys) / min(ys) > 20  # the models differ by ~10x: a log axis keeps pinhole readable
    img = line_chart(curves, title="Solve time against views", x_label="views",
                     y_label="seconds, median of 3" + (" (log scale)" if log_y else ""), log_y=log_y,
                     subtitle=f"calibcoach solve() on views spread over {SOLVE_CAPTURE}, OpenCV on 1 thread")
    save(img, RESULTS / "solve_time.png")


# --- 3. replay ------------------------------------------------------------------------------------
def replay_section(recording: Path, image_folder: Path | None) -> list[str]:
    source = open_source(recording)
    session, stats = run_replay(source, BoardSpec.from_dict(dict(source.info.board)), SessionSettings())
    _, finish_ms = ms_of(session.finish)
    lines = ["| source | frames read | tracked | replay s | frames read/s | finish() s |", "|---|---|---|---|---|---|",
             f"| recording {recording.name} | {stats.frames_read} | {stats.tracked} | {stats.seconds:.1f} "
             f"| {stats.frames_read / stats.seconds:.1f} | {finish_ms / 1e3:.2f} |"]
    if image_folder is not None:
        _, folder_stats = run_replay(open_source(image_folder), BoardSpec())
        lines.append(f"| folder {image_folder.parent.name}/{image_folder.name} | {folder_stats.frames_read} | {folder_stats.tracked} "
                     f"| {folder_stats.seconds:.1f} | {folder_stats.frames_read / folder_stats.seconds:.1f} | - |")
    lines.append("\n`run_replay` with default settings and no viewer attached (saving session.rrd adds a logging "
                 "thread; see Rerun log_frame above). The recording is detected frame by frame; the folder's held boards are tracked.")
    if stats.stopped_early:
        lines.append("\nThe recording's replay met the stop rule early: frames after it were never read.")
    return lines


# --- report ---------------------------------------------------------------------------------------
def machine_line() -> str:
    cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")), platform.processor() or "unknown CPU")
    load = os.getloadavg()[0]
    return (f"{date.today()}, {len(os.sched_getaffinity(0))} cores (nproc), {cpu}, OpenCV {cv2.__version__} "
            f"(default {DEFAULT_THREADS} threads); load average {load:.1f} at start: another process may hold a core")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--folder", type=Path, help="an image folder to replay as well (read sparsely)")
    parser.add_argument("--skip-solve", action="store_true", help="only the per-frame section")
    args = parser.parse_args()
    lines = ["# Speed", "", machine_line(), "", "## Per-frame cost", ""]
    per_frame, results = per_frame_section()
    per_frame_plot(results)
    lines += per_frame + ["", NOTES_PER_FRAME, "", "![per frame](speed_per_frame.png)"]
    if not args.skip_solve:
        recording = solve_capture()
        solve_lines, curves = solve_section(recording)
        solve_plot(curves)
        lines += ["", "## Solve time", ""] + solve_lines + ["", "![solve time](solve_time.png)"]
        lines += ["", "## Replay", ""] + replay_section(recording, args.folder)
    text = "\n".join(lines) + "\n"
    (RESULTS / "speed.md").write_text(text)
    print(text)
    return 0


NOTES_PER_FRAME = (
    "Each frame timed on its own, after one warm-up frame (the session step and logging: their first frame "
    f"is left out); each frame's time is the fastest of {ROUNDS} rounds. calibcoach detection, the session "
    "step and logging run with OpenCV on one thread, as a replay runs them. Logging saves session.rrd only "
    "(viewer mode none). 1 core = detect + step + log_frame in series. "
    f"{CORES} cores = replay: detection on worker threads, the session step on one thread and logging on "
    "another (app/viewer_thread.py), so the slowest of those or the total work over the cores binds. "
    "Live (app/live.py): one thread detects (with OpenCV's two threads: the corners are bit-identical, the "
    "time is the bare 2-thread detectBoard's), steps and logs the overlays (log_frame without the image) while "
    "the capture thread logs every camera frame's preview image; when the processing thread is slower than "
    f"the camera it drops frames rather than queueing them. Ten frames are too few for the session's "
    "incremental solves (from 6 accepted views on; see the solve times), which add to the step of some frames "
    "in a long session. Live recording (PNG encoding) is not included."
)


if __name__ == "__main__":
    raise SystemExit(main())
