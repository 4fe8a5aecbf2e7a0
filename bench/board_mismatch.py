"""What the board diagnosis says where it must say nothing, and where it must name the board.

The diagnosis (`coverage.board_diagnosis.diagnose_board_mismatch`) runs live on a few frames once 45 have
come without the board (app/board_watch.py) and at the end of a capture that never showed it. Said
to the wrong person it sends them after the wrong fix, so this bench measures both sides:

1. Frames without a usable board (< 6 corners) of footage that shows the *right* board elsewhere
   (every render in bench/cache, the bundled recordings, the real captures with their own boards):
   three at a time, the way the live watch samples them, asked in its `specific_only` mode. Any
   answer there is a false claim ("pass --dictionary ..." for a stray look-alike, say). Per source:
   the most markers any dictionary showed in one such frame, and the claims made.
2. Prints of other sizes under the default board (rendered by OpenCV, and caliscope's real 4x5
   print given only its dictionary): the layout named.
3. A real plain chessboard (BoofCV's photos): named as one.

    .venv/bin/python bench/board_mismatch.py [--data ../shared/data]

Writes bench/results/board_mismatch.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT.parent / "tests" / "app"))

from _boards import board_photo  # noqa: E402  (tests/app/_boards.py: the board printed in a 720p frame)

from calibcoach.coverage.board import BoardSpec  # noqa: E402
from calibcoach.coverage.board_diagnosis import _DISTINCT_DICTIONARIES, diagnose_board_mismatch  # noqa: E402
from calibcoach.coverage.detector import CharucoBoardDetector, _aruco_parameters  # noqa: E402

FRAMES_READ = 600  # of each source, every STEP-th
STEP = 5
CALISCOPE = BoardSpec(4, 5, 54.0, 40.5, "DICT_4X4_1000")
WPICAL = BoardSpec(12, 8, 15.585, 12.124, "DICT_5X5_1000")


def greys_of(path: Path) -> Iterator[np.ndarray]:
    """Every STEP-th grey frame of a folder of images or a video, up to FRAMES_READ frames."""
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
        for f in files[:FRAMES_READ:STEP]:
            grey = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if grey is not None:
                yield grey
        return
    capture = cv2.VideoCapture(str(path))
    for index in range(FRAMES_READ):
        ok, frame = capture.read()
        if not ok:
            return
        if index % STEP == 0:
            yield cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)


def sources(data: Path) -> list[tuple[str, Path, BoardSpec]]:
    found = [(p.name, p / "frames" if (p / "frames").is_dir() else p / "capture.avi", BoardSpec())
             for p in sorted((ROOT / "cache").iterdir()) if p.is_dir()]
    found += [(f"recording {p.name}", p / "frames", BoardSpec()) for p in sorted((ROOT.parent / "recordings").iterdir())
              if (p / "frames").is_dir()]
    for name, path, spec in (("caliscope cam_0 (inverted 4x5)", data / "caliscope_webcam_charuco_4x5" / "video" / "cam_0.mp4",
                              BoardSpec(4, 5, 54.0, 40.5, "DICT_4X4_1000", inverted=True)),
                             ("wpical phone video (12x8)", data / "wpical_phone_video_charuco_12x8" / "testcalibration.mp4", WPICAL)):
        if path.exists():
            found.append((name, path, spec))
    return found


def most_markers(greys: list[np.ndarray]) -> tuple[str, int]:
    """The dictionary with the most markers in one frame, and how many."""
    best = ("-", 0)
    for name in _DISTINCT_DICTIONARIES:
        detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)), _aruco_parameters(inverted=True))
        for grey in greys:
            ids = detector.detectMarkers(grey)[1]
            if ids is not None and len(ids) > best[1]:
                best = (name, len(ids))
    return best


def boardless(name: str, path: Path, spec: BoardSpec) -> str:
    detector = CharucoBoardDetector(spec)
    greys = [g for g in greys_of(path) if detector.detect(g).corner_count < 6]
    triples = [greys[i:i + 3] for i in range(0, len(greys) - 2, 3)]
    claims = [str(e) for e in (diagnose_board_mismatch(spec, t, specific_only=True) for t in triples) if e is not None]
    dictionary, most = most_markers(greys) if greys else ("-", 0)
    said = "; ".join(sorted(set(c[:90] for c in claims))) or "-"
    return f"| {name} | {len(greys)} | {len(triples)} | {dictionary} {most} | {len(claims)} | {said} |"


def sized(name: str, greys: list[np.ndarray], spec: BoardSpec, expected: str) -> str:
    start = time.perf_counter()
    error = diagnose_board_mismatch(spec, greys)
    seconds = time.perf_counter() - start
    said = "" if error is None else str(error)
    named = said.split("pass ")[-1].split(" (")[0] if "they form the corners" in said else "-"
    return f"| {name} | {expected} | {named} | {'yes' if named.startswith(expected) else '**no**'} | {seconds:.2f} |"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent.parent / "shared" / "data")
    args = parser.parse_args()
    lines = ["# Board diagnosis: false claims on frames without the board, and sizes named", "",
             f"`bench/board_mismatch.py`: every {STEP}th of the first {FRAMES_READ} frames of each source; the frames with "
             "fewer than 6 corners of the source's own board, three at a time as the live watch samples them "
             "(`specific_only`). Any claim there is false: the right board is what the source shows.", "",
             "| source | frames without the board | diagnoses | most markers in one frame | claims | what was claimed |",
             "|---|---|---|---|---|---|"]
    for name, path, spec in sources(args.data):
        lines.append(boardless(name, path, spec))
        print(lines[-1], flush=True)
    lines += ["", "Prints of other sizes under the default 8x11 board (OpenCV's print in a 720p frame; caliscope's real "
              "print given only its dictionary, six frames showing it):", "",
              "| print | expected | named | right | seconds |", "|---|---|---|---|---|"]
    for squares, legacy in (((5, 7), False), ((7, 5), False), ((6, 9), False), ((10, 7), False), ((4, 5), False), ((6, 8), True)):
        photo = board_photo(BoardSpec(squares_x=squares[0], squares_y=squares[1]), legacy=legacy)
        expected = f"--squares {squares[0]}x{squares[1]}" + (" --legacy" if legacy else "")
        lines.append(sized(f"{squares[0]}x{squares[1]}{' legacy' if legacy else ''} render", [photo], BoardSpec(), expected))
        print(lines[-1], flush=True)
    video = args.data / "caliscope_webcam_charuco_4x5" / "video" / "cam_0.mp4"
    if video.exists():
        own = CharucoBoardDetector(BoardSpec(4, 5, 54.0, 40.5, "DICT_4X4_1000"))
        showing = [g for g in greys_of(video) if own.detect(g).corner_count >= 6][:6]
        lines.append(sized("caliscope cam_0, real inverted 4x5", showing, BoardSpec(dictionary="DICT_4X4_1000"), "--squares 4x5"))
        print(lines[-1], flush=True)
    chess = args.data / "boofcv_sony_hx5v_chess"
    if chess.is_dir():  # a real plain chessboard (BoofCV's 13 photos, 5x7 squares), three at a time as the watch samples
        photos = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in sorted(chess.glob("frame*.jpg"))]
        said = [str(diagnose_board_mismatch(BoardSpec(), photos[i:i + 3], specific_only=True)) for i in range(0, len(photos) - 2, 3)]
        named = sum("a plain chessboard" in s for s in said)
        lines += ["", "A real plain chessboard (BoofCV's Sony HX5V photos, 5x7 squares) under the default board, three "
                  f"photos at a time: named a plain chessboard in {named} of {len(said)} diagnoses"
                  + (f" ({said[0].split(', not a ChArUco')[0]})" if named else "")]
        print(lines[-1], flush=True)
    (ROOT / "results" / "board_mismatch.md").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
