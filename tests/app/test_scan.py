"""The sparse scan: still stretches of a sequence are looked at once per stride, changes are found
exactly, independent stills are all read, and what it yields is what a dense read detects."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from calibcoach.app.replay import run_replay
from calibcoach.app.scan import Look, SparseScan, compare_views, same_view
from calibcoach.app.session import SessionSettings
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector, Detection
from calibcoach.coverage.select import SelectorSettings
from calibcoach.drivers.base import Frame
from calibcoach.drivers.replay import ImageFolderSource

SIZE = (1280, 720)


def _locked_detector(spec: BoardSpec):
    detector, lock = CharucoBoardDetector(spec), threading.Lock()

    def detect(frame: Frame) -> Detection:
        with lock:
            return detector.detect(frame.grey())

    return detect


def _held_views(recordings_dir: Path, tmp_path: Path, views: list[int], hold: int) -> Path:
    """A folder in which each listed demo frame is held still for `hold` frames (links, not copies)."""
    frames = recordings_dir / "demo_webcam720_careful" / "frames"
    folder = tmp_path / "held"
    folder.mkdir()
    n = 0
    for view in views:
        for _ in range(hold):
            (folder / f"{n:04d}.png").symlink_to(frames / f"{view:06d}.png")
            n += 1
    return folder


def test_a_held_board_is_looked_at_once_per_stride_and_the_change_is_found_exactly(recordings_dir: Path, tmp_path: Path) -> None:
    # frames 0-16 hold one view, 17-33 another: keys 0, 8, 16, 24, 32, 33; the change between
    # 16 and 24 is bisected down to 16 | 17, and the still stretches in between are passed over.
    folder = _held_views(recordings_dir, tmp_path, [0, 30], hold=17)
    source = ImageFolderSource(folder)
    scan = SparseScan(source, _locked_detector(BoardSpec()), stride=8)
    looked = list(scan)
    assert [f.index for f, _ in looked] == [0, 8, 16, 17, 18, 20, 24, 32, 33]
    assert scan.passed_over == 34 - 9
    assert all(d.corner_count >= 6 for _, d in looked)
    # what the scan yields is exactly what a dense read detects on those frames
    dense = CharucoBoardDetector(BoardSpec())
    for frame, detection in looked:
        again = dense.detect(source.load(frame.index).grey())
        assert np.array_equal(again.ids, detection.ids) and np.array_equal(again.corners_px, detection.corners_px)


def test_independent_stills_are_all_read(shared_data: Path) -> None:
    spec = BoardSpec(20, 20, 4.0, 3.2, "DICT_4X4_1000")
    source = ImageFolderSource(shared_data / "pycamset_charuco_3cam" / "2")
    scan = SparseScan(source, _locked_detector(spec), stride=8)
    indices = [f.index for f, _ in scan]
    assert indices == list(range(source.frame_count_for_random_access))
    assert scan.passed_over == 0


def _look(index: int, corners: np.ndarray | None, thumb_grey: float, markers: int = 0) -> Look:
    if corners is None:
        detection = Detection.empty(np.arange(markers, dtype=np.int32))
    else:
        ids = np.arange(len(corners), dtype=np.int32)
        detection = Detection(corners.astype(np.float32), ids, np.zeros((len(corners), 3), np.float32), ids)
    return Look(index, None, None, detection, np.full((18, 32), thumb_grey, np.float32))


def test_same_view_rules() -> None:
    grid = np.stack(np.meshgrid(np.arange(7) * 40.0 + 300, np.arange(10) * 40.0 + 100), -1).reshape(-1, 2)
    diag = float(np.hypot(*SIZE))
    still = _look(0, grid, 100), _look(8, grid + 0.006 * diag, 100)
    assert same_view(*still, SIZE)
    assert not same_view(still[0], _look(8, grid + 0.012 * diag, 100), SIZE)  # moved too far
    # detection dropped a third of the corners: the board is held, but frames between may find more
    assert compare_views(still[0], _look(8, grid[:40], 100), SIZE) == "held"
    assert compare_views(still[0], _look(8, grid[:66], 100), SIZE) == "same"  # a steady detection
    assert not same_view(still[0], _look(8, grid[:30], 100), SIZE)  # most corners went: it slid out of view
    assert not same_view(still[0], _look(8, None, 100), SIZE)  # the board went
    # no board at either end: an unchanged scene is the same view; a changed one only in footage
    assert same_view(_look(0, None, 100), _look(8, None, 104), SIZE)
    assert not same_view(_look(0, None, 100), _look(8, None, 140), SIZE)
    assert compare_views(_look(0, None, 100), _look(8, None, 140), SIZE, video=True) == "away"
    assert compare_views(_look(0, None, 100, markers=3), _look(8, None, 140), SIZE, video=True) == "different"  # markers: a board is near


def test_replay_of_a_held_folder_passes_over_the_repeats_unless_every_frame(recordings_dir: Path, tmp_path: Path) -> None:
    folder = _held_views(recordings_dir, tmp_path, [0, 30, 66, 114], hold=12)
    # a budget of 4 frames: 4 views and their repeats are plenty to choose from, so no second pass
    settings = SessionSettings(selector=SelectorSettings(max_frames=4), stop_when_done=False)  # read to the end
    sparse, stats = run_replay(ImageFolderSource(folder), BoardSpec(), settings)
    dense, dense_stats = run_replay(ImageFolderSource(folder), BoardSpec(), settings, every_frame=True)
    assert stats.passed_over >= 12 and stats.frames_read + stats.passed_over == 48
    assert dense_stats.passed_over == 0 and dense_stats.frames_read == 48
    # the same views are kept either way: what was passed over only repeated them
    assert {v.frame_index // 12 for v in sparse.views} == {v.frame_index // 12 for v in dense.views}


def test_a_capture_short_of_usable_frames_gets_a_second_pass_near_the_boards(recordings_dir: Path, tmp_path: Path) -> None:
    # 48 frames can never give the default 60-frame budget 1.5x its size to choose from: the frames
    # passed over within 4 of a usable board are read after all (here: every one of them)
    folder = _held_views(recordings_dir, tmp_path, [0, 30, 66, 114], hold=12)
    session, stats = run_replay(ImageFolderSource(folder), BoardSpec())
    assert session.short_of_choice()
    assert stats.passed_over == 0 and stats.frames_read == 48


@pytest.mark.parametrize("stride", [1, 3])
def test_short_strides_read_everything_that_changes(recordings_dir: Path, tmp_path: Path, stride: int) -> None:
    folder = _held_views(recordings_dir, tmp_path, [0, 30], hold=5)
    scan = SparseScan(ImageFolderSource(folder), _locked_detector(BoardSpec()), stride=stride)
    indices = [f.index for f, _ in scan]
    assert indices[0] == 0 and indices[-1] == 9 and {4, 5} <= set(indices)
    assert len(indices) + scan.passed_over == 10


def test_what_is_read_does_not_depend_on_the_number_of_workers(recordings_dir: Path, tmp_path: Path) -> None:
    folder = _held_views(recordings_dir, tmp_path, [0, 30, 66, 114], hold=9)
    runs = []
    for workers in (1, 2, 2):
        read: list[int] = []
        session, stats = run_replay(ImageFolderSource(folder), BoardSpec(), SessionSettings(selector=SelectorSettings(max_frames=4)),
                                    workers=workers, on_outcome=lambda outcome, frame, read=read: read.append(frame.index))
        runs.append((read, [v.frame_index for v in session.views], stats.passed_over))
    assert runs[0] == runs[1] == runs[2]
    assert runs[0][2] > 0
