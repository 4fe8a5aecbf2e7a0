"""The live hint for a camera showing some other board than the one configured (app/board_watch.py):
real detection on rendered boards, and the live command on a mirrored folder (the Assistant's steps)."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from _boards import board_photo

from calibcoach.app import board_watch, session_finish
from calibcoach.app.board_watch import ANSWER_AFTER, CHECK_EVERY, BoardWatch
from calibcoach.app.cli import main
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector
from calibcoach.coverage.select import SelectorSettings
from calibcoach.drivers.base import Frame


def steps(images: list[np.ndarray]) -> tuple[BoardWatch, list[str]]:
    """The watch's hint after each of `images`, each detected with the default board as a session would
    (the same image once: the watch reads only what the detection found)."""
    watch, detector, detections = BoardWatch(SelectorSettings().min_corners), CharucoBoardDetector(BoardSpec()), {}
    hints = []
    for i, image in enumerate(images):
        if id(image) not in detections:
            detections[id(image)] = detector.detect(image)
        hints.append(watch.see(Frame(i, i * 33_333_333, image), detections[id(image)], BoardSpec()))
    return watch, hints


def test_a_mirrored_camera_is_named_once_enough_frames_came_without_the_board() -> None:
    mirrored = cv2.flip(board_photo(BoardSpec()), 1)
    watch, hints = steps([mirrored] * (CHECK_EVERY + ANSWER_AFTER + 5))
    said_at = CHECK_EVERY + ANSWER_AFTER - 1  # diagnosed at the 45th frame, its answer taken 30 frames later
    assert hints[:said_at] == [""] * said_at  # not while a board may still be coming into view
    assert all("mirrored left to right" in h and "ffmpeg -vf hflip" in h for h in hints[said_at:])
    assert watch.checks == 1  # said once, then kept: no second diagnosis


def test_a_smaller_print_than_configured_is_said_to_be_some_other_board() -> None:
    _watch, hints = steps([board_photo(BoardSpec(squares_x=5, squares_y=7))] * (CHECK_EVERY + ANSWER_AFTER))
    assert "no corners match a 8x11 squares" in hints[-1] and "--squares 5x7" in hints[-1]


def test_the_right_board_far_or_partial_is_not_called_another_board(monkeypatch: pytest.MonkeyPatch) -> None:
    """A single marker of the right board (the rest out of view) gives no corners: no cause to name. A
    few more give a corner or four, the sign of the right board: not even diagnosed (1-2 s each)."""
    photo = board_photo(BoardSpec())
    one_marker = np.full_like(photo, 128)
    one_marker[60:160, 400:520] = photo[60:160, 400:520]  # the top-left square and one marker
    watch, hints = steps([one_marker] * (CHECK_EVERY + 1))
    assert watch.checks == 1 and hints[-1] == ""
    diagnosed: list[int] = []
    real = board_watch.diagnose_board_mismatch
    monkeypatch.setattr(board_watch, "diagnose_board_mismatch", lambda *a, **k: diagnosed.append(1) or real(*a, **k))
    four_corners = np.full_like(photo, 128)
    four_corners[60:260, 400:560] = photo[60:260, 400:560]
    watch, hints = steps([one_marker] * (CHECK_EVERY + 1) + [four_corners] * (2 * CHECK_EVERY + 1))
    assert watch.checks == 2 and len(diagnosed) == 1 and set(hints) == {""}


def test_a_mirrored_board_shown_late_is_named_at_the_next_diagnosis() -> None:
    """The camera pointed at an empty scene first: nothing board-like, nothing said, and diagnosed less
    often (after 45, then 90 more frames); the board comes later, and the next diagnosis looks at the
    frames since the last."""
    empty = np.full((720, 1280), 128, np.uint8)
    mirrored = cv2.flip(board_photo(BoardSpec()), 1)
    named_at = CHECK_EVERY + 2 * CHECK_EVERY + ANSWER_AFTER  # the second diagnosis's answer
    watch, hints = steps([empty] * (CHECK_EVERY + 10) + [mirrored] * (2 * CHECK_EVERY + ANSWER_AFTER))
    assert watch.checks == 2
    assert set(hints[: named_at - 1]) == {""} and "mirrored" in hints[named_at - 1] and "mirrored" in hints[-1]


def test_a_4k_camera_is_diagnosed_on_halved_frames(monkeypatch: pytest.MonkeyPatch) -> None:
    mirrored = cv2.resize(cv2.flip(board_photo(BoardSpec()), 1), (3840, 2160), interpolation=cv2.INTER_CUBIC)
    widths: list[int] = []
    real = board_watch.diagnose_board_mismatch
    monkeypatch.setattr(board_watch, "diagnose_board_mismatch",
                        lambda spec, greys, **k: widths.extend(g.shape[1] for g in greys) or real(spec, greys, **k))
    watch, hints = steps([mirrored] * (CHECK_EVERY + ANSWER_AFTER))
    assert widths == [1920] * 3 and "mirrored left to right" in hints[-1]


def test_nothing_is_said_when_the_board_turns_up_and_watching_stops_for_good() -> None:
    empty = np.full((720, 1280), 128, np.uint8)
    right = board_photo(BoardSpec())
    watch, hints = steps([empty] * (CHECK_EVERY + 1) + [right] * 3 + [empty] * (2 * CHECK_EVERY + 2))
    assert set(hints) == {""}
    assert watch.checks == 1  # the empty scene was diagnosed once (nothing board-like); none after the board


def test_the_diagnosis_runs_beside_the_frames_and_is_answered_at_a_fixed_frame(monkeypatch: pytest.MonkeyPatch) -> None:
    """The frame loop goes on while a diagnosis runs (it stalled the live preview 0.25-1 s at each check),
    and its answer is taken ANSWER_AFTER frames later however long it took: the same frame live and in a
    replay. A diagnosis slower than that makes the loop wait there, not skip it."""
    mirrored = cv2.flip(board_photo(BoardSpec()), 1)
    real = board_watch.diagnose_board_mismatch
    released = threading.Event()
    ran_beside: list[bool] = []

    def held_until_released(*args, **kwargs):
        ran_beside.append(released.wait(timeout=10.0))  # in the frame loop it would wait here for nothing
        return real(*args, **kwargs)

    monkeypatch.setattr(board_watch, "diagnose_board_mismatch", held_until_released)
    watch, detection = BoardWatch(SelectorSettings().min_corners), CharucoBoardDetector(BoardSpec()).detect(mirrored)
    hints = []
    for i in range(CHECK_EVERY + ANSWER_AFTER + 2):
        if i == CHECK_EVERY + 10:
            released.set()  # ten frames after the diagnosis started
        hints.append(watch.see(Frame(i, i * 33_333_333, mirrored), detection, BoardSpec()))
    assert ran_beside == [True]
    said_at = CHECK_EVERY + ANSWER_AFTER - 1
    assert set(hints[:said_at]) == {""} and all("mirrored" in h for h in hints[said_at:])

    def slow(*args, **kwargs):
        time.sleep(0.5)  # longer than the 30 frames take here
        return real(*args, **kwargs)

    monkeypatch.setattr(board_watch, "diagnose_board_mismatch", slow)
    _watch, slow_hints = steps([mirrored] * (CHECK_EVERY + ANSWER_AFTER + 2))
    assert slow_hints == hints


def test_a_board_shown_while_a_diagnosis_runs_is_never_called_another(monkeypatch: pytest.MonkeyPatch) -> None:
    """The mirrored frames' diagnosis is still to be answered when the configured board turns up: its
    answer is not taken, and nothing is said; a capture ending before the answer's frame takes it then."""
    mirrored, right = cv2.flip(board_photo(BoardSpec()), 1), board_photo(BoardSpec())
    watch, hints = steps([mirrored] * (CHECK_EVERY + 5) + [right] * 3)
    assert watch.checks == 1 and set(hints) == {""} and watch.finding is None
    watch, hints = steps([mirrored] * (CHECK_EVERY + 5))
    assert set(hints) == {""} and watch.finding is None
    watch.settle()  # the capture's end (Assistant.flush)
    assert "mirrored left to right" in str(watch.finding) and "mirrored" in watch.hint


def test_live_says_the_stream_is_mirrored_while_it_runs(recordings_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    """A webcam in mirror mode, live: the status says so on a line of its own long before the capture ends,
    and the capture's end says it again from that one diagnosis (1-2 s), not from a second."""
    diagnosed: list[str] = []
    for module in (board_watch, session_finish):
        real = module.diagnose_board_mismatch
        monkeypatch.setattr(module, "diagnose_board_mismatch",
                            lambda *a, _m=module.__name__, _real=real, **k: diagnosed.append(_m) or _real(*a, **k))
    folder = tmp_path / "mirrored"
    folder.mkdir()
    detector = CharucoBoardDetector(BoardSpec())
    greys = [cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
             for path in sorted((recordings_dir / "demo_webcam720_careful" / "frames").glob("*.png"))]
    showing = [grey for grey in greys if detector.detect(grey).corner_count >= 20]  # 42 of the 120 frames
    for i in range(CHECK_EVERY + ANSWER_AFTER + 25):  # mirrored, the first ones played twice
        cv2.imwrite(str(folder / f"{i:04d}.png"), cv2.flip(showing[i % len(showing)], 1))
    steps_path = tmp_path / "steps.jsonl"
    code = main(["live", "--source", str(folder), "--out", str(tmp_path / "o"), "--no-viewer", "--speed", "0.35",
                 "--guidance-jsonl", str(steps_path)])
    assert code == 2  # and the capture's end says it again, as an error
    lines = [json.loads(line) for line in steps_path.read_text().splitlines()]
    hinted = [i for i, s in enumerate(lines) if "mirrored left to right" in s["guidance"]["hint"]]
    said_at = CHECK_EVERY + ANSWER_AFTER - 1
    assert len(lines) > said_at and hinted == list(range(said_at, len(lines)))  # from the first diagnosis's answer on
    said = [line for line in capsys.readouterr().err.splitlines() if "mirrored left to right" in line]
    assert said[0].startswith("calibcoach: No corners of the configured board yet: the images are mirrored")
    assert said[-1].startswith("calibcoach: error: the images are mirrored left to right")
    assert diagnosed == ["calibcoach.app.board_watch"]
