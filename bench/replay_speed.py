"""Replay speed: `calibcoach calibrate` on a folder versus the plain loop, measured in one run.

The plain loop is what a user would write with OpenCV alone: imread + detectBoard on every frame,
then one calibrateCamera over every frame with >= 6 corners. Both run in this process, taking
turns run by run, on the same files (the page cache is warmed first, so neither pays for the disk).

    .venv/bin/python bench/replay_speed.py [FOLDER] [--runs 3] [--style careful|sloppy]

Without FOLDER, a 784-frame 720p handheld capture at 30 fps is rendered once into bench/cache/
(~5 min). Prints one line per method, how many frames calibcoach read and tracked, and the
ratio calibcoach / plain (the target is <= 0.5).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from calibcoach.coverage.board import BoardSpec
from calibcoach.drivers.png_fast import row_filters
from calibcoach.drivers.replay import IMAGE_EXTENSIONS


def _greys(source: list[Path] | Path) -> Iterator[np.ndarray]:
    """The grey frames of a folder's files (imread) or of a video (VideoCapture, as a user would read it)."""
    if isinstance(source, list):
        for f in source:
            yield cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        return
    capture = cv2.VideoCapture(str(source))
    while True:
        ok, frame = capture.read()
        if not ok:
            return
        yield cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)


def plain_loop(source: list[Path] | Path, spec: BoardSpec) -> tuple[float, int]:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    board = spec.cv_board()
    detector = cv2.aruco.CharucoDetector(board, cv2.aruco.CharucoParameters(), params)
    start = time.perf_counter()
    obj, img = [], []
    size = None
    for grey in _greys(source):
        size = grey.shape[::-1]
        corners, ids, _, _ = detector.detectBoard(grey)
        if ids is not None and len(ids) >= 6:
            o, i = board.matchImagePoints(corners, ids)
            obj.append(o.reshape(-1, 1, 3))
            img.append(i.reshape(-1, 1, 2))
    try:
        cv2.calibrateCamera(obj, img, size, None, None)
    except cv2.error:
        pass  # a degenerate frame (messy footage) defeats OpenCV's initialisation: the loop still spent the time
    return time.perf_counter() - start, len(obj)


def png_filters(path: Path) -> str:
    """Which PNG row filters a file uses, e.g. "Sub 720" (OpenCV's default) or "Average 404, Paeth 306"."""
    filters = row_filters(path.read_bytes()) if path.suffix.lower() == ".png" else None
    if filters is None:
        return "not an 8-bit grey or RGB PNG (decoded by OpenCV)"
    counts = np.bincount(filters, minlength=5)
    return ", ".join(f"{name} {n}" for name, n in zip(("None", "Sub", "Up", "Average", "Paeth"), counts, strict=False) if n)


def calibcoach_run(folder: Path) -> tuple[float, str]:
    """Seconds for the whole command, and its line saying how many frames it read."""
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        done = subprocess.run([sys.executable, "-m", "calibcoach.app", "calibrate", str(folder), "--out", out, "--quiet"],
                              check=False, capture_output=True, text=True)
        seconds = time.perf_counter() - start
    said = next((line for line in done.stderr.splitlines() if line.startswith("calibcoach: read ")), done.stderr[-300:])
    return seconds, said


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path, nargs="?", help="a folder of images or a video file (default: render a folder)")
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--style", default="careful", choices=("careful", "sloppy", "frontal"),
                        help="handheld style of the rendered capture")
    args = parser.parse_args()
    if args.folder is None:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from accuracy import rendered  # bench/accuracy.py renders and caches captures

        args.folder = rendered("webcam720", args.style, seconds=784 / 30, fps=30.0) / "frames"
    video = args.folder.is_file()  # a video file: read with VideoCapture, one frame after the other
    files = [args.folder] if video else sorted(p for p in args.folder.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
    if not files:
        inside = args.folder / "frames"
        hint = f"; a render's cache keeps its images in {inside}: pass that" if inside.is_dir() else ""
        raise SystemExit(f"replay_speed: no images in {args.folder}{hint}")
    for f in files:  # warm the page cache for both
        f.read_bytes()
    # The two alternate, so that the machine's own drift (~15% over a day on a shared host) falls on
    # both alike; each pair gives a ratio, and the spread of those says how far one run can be trusted.
    plain, ours = [], []
    for _ in range(args.runs):
        plain.append(plain_loop(args.folder if video else files, BoardSpec()))
        ours.append(calibcoach_run(args.folder))
    p, o = float(np.median([t for t, _ in plain])), float(np.median([t for t, _ in ours]))
    pairs = [t_ours / t_plain for (t_plain, _), (t_ours, _) in zip(plain, ours, strict=True)]
    read = "VideoCapture.read" if video else "imread"
    print(f"plain loop ({read} + detectBoard on every frame + calibrateCamera on {plain[0][1]}): {p:.2f} s")
    print(f"calibcoach calibrate (whole command, start-up included):          {o:.2f} s")
    print(f"  {ours[0][1]}")
    if not video:
        print(f"  PNG rows of {files[0].name}: {png_filters(files[0])} (how they were filtered decides the decoding cost, bench/results/replay_speed.md)")
    # The medians of each side's times can pair a fast run of one with a slow run of the other; the
    # median of the run-by-run ratios cannot, and is the number to compare with 0.5.
    print(f"ratio calibcoach / plain: {float(np.median(pairs)):.2f} median of the runs' ratios ({', '.join(f'{r:.2f}' for r in pairs)}); "
          f"of the median times {o / p:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
