"""The held-frame scan: a held board is tracked to the accuracy of a fresh detection, every 5th
frame and every change is detected in full, fast transits of footage are sampled and never used,
independent stills are all detected, and a replay's tracked frames join its final solve."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from calibcoach.app import scan
from calibcoach.app.replay import run_replay
from calibcoach.app.scan import (
    _TRANSIT_SAMPLE,
    _TRANSIT_SAMPLE_ONCE_SEEN,
    REDETECT_EVERY,
    HeldFrameScan,
    thumbnail,
)
from calibcoach.app.scan_stream import detected_frames
from calibcoach.app.session import SessionSettings
from calibcoach.coverage import detector as detector_module
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector, Detection
from calibcoach.coverage.select import SelectorSettings
from calibcoach.drivers.replay import ImageFolderSource, open_source

SETTLED = BoardSpec().with_detected(legacy=False, inverted=False)  # as a replay settles it on its first frames


def _demo_grey(recordings_dir: Path, index: int) -> np.ndarray:
    return cv2.imread(str(recordings_dir / "demo_webcam720_careful" / "frames" / f"{index:06d}.png"), cv2.IMREAD_GRAYSCALE)


def _shifted(grey: np.ndarray, dx: float, dy: float, rng: np.random.Generator) -> np.ndarray:
    """The frame moved by a sub-pixel (dx, dy), with fresh sensor noise: a held board's next frame."""
    moved = cv2.warpAffine(grey.astype(np.float32), np.float32([[1, 0, dx], [0, 1, dy]]), grey.shape[::-1],
                           flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    return np.clip(moved + rng.normal(0, 1.0, grey.shape), 0, 255).astype(np.uint8)


def _write(folder: Path, greys: list[np.ndarray]) -> Path:
    folder.mkdir()
    for n, grey in enumerate(greys):
        cv2.imwrite(str(folder / f"{n:04d}.png"), grey)
    return folder


def _hold(recordings_dir: Path, view: int, frames: int, seed: int) -> list[np.ndarray]:
    """`frames` frames of one demo view under a hand's tremor: a random walk of ~0.4 px per frame."""
    rng = np.random.default_rng(seed)
    grey = _demo_grey(recordings_dir, view)
    walk = np.cumsum(rng.normal(0, 0.3, (frames, 2)), axis=0)
    return [_shifted(grey, dx, dy, rng) for dx, dy in walk]


@pytest.mark.parametrize("size", [(1280, 720), (1920, 1080), (640, 360), (160, 90), (640, 480), (1279, 720)])
def test_thumbnails_are_opencvs_area_resize_bit_for_bit(recordings_dir: Path, size: tuple[int, int]) -> None:
    # The scan's decisions hang on thumbnail differences against fixed shares: the C block means must
    # be OpenCV's numbers exactly, ties rounded to even included (half-up rounding differed on ~4% of
    # frames), and sizes OpenCV treats otherwise (2x2 cells, fractional cells) must go to OpenCV.
    assert scan._block_means is not None, "the C extension coverage/_block_mean.c was not built (pip install -e .)"
    rng = np.random.default_rng(7)
    frames = [cv2.resize(_demo_grey(recordings_dir, i), size, interpolation=cv2.INTER_AREA) for i in (0, 40, 80)]
    frames += [rng.integers(0, 256, size[::-1], dtype=np.uint8), np.full(size[::-1], 128, np.uint8)]
    for grey in frames:
        expected = cv2.resize(grey, (80, 45), interpolation=cv2.INTER_AREA).astype(np.float32)
        got = thumbnail(grey)
        assert got.dtype == np.float32 and got.shape == (45, 80)
        np.testing.assert_array_equal(got, expected)


def test_thumbnails_without_the_c_extension_are_the_same(recordings_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    grey = _demo_grey(recordings_dir, 40)
    with_c = thumbnail(grey)
    # a mirrored view is not contiguous: OpenCV thumbnails it, and its contiguous copy the C loop
    np.testing.assert_array_equal(thumbnail(grey[:, ::-1]), thumbnail(np.ascontiguousarray(grey[:, ::-1])))
    monkeypatch.setattr(scan, "_block_means", None)
    np.testing.assert_array_equal(thumbnail(grey), with_c)


def test_a_held_board_is_tracked_to_the_accuracy_of_a_fresh_detection(recordings_dir: Path, tmp_path: Path) -> None:
    folder = _write(tmp_path / "held", _hold(recordings_dir, 0, 30, seed=1))
    spec = SETTLED
    scan = HeldFrameScan(iter(ImageFolderSource(folder)), lambda: CharucoBoardDetector(spec))
    seen = list(scan)
    # the frames on the re-detection grid detected, every other frame tracked from the one before
    grid = list(range(0, 30, REDETECT_EVERY))
    assert len(grid) >= 2 and [s.frame.index for s in seen if s.tracked_from is None] == grid
    assert scan.tracked == 30 - len(grid) and scan.detected == len(grid) and scan.skipped == 0
    fresh = CharucoBoardDetector(spec)
    gaps = []
    for s in seen:
        if s.tracked_from is not None:
            assert s.tracked_from == s.frame.index - 1 and 0 < s.shift_px < 3.0
            again = fresh.detect(s.frame.grey())
            _shared, ia, ib = np.intersect1d(s.detection.ids, again.ids, return_indices=True)
            assert ia.size >= 0.9 * again.corner_count
            gaps.append(np.linalg.norm(s.detection.corners_px[ia] - again.corners_px[ib], axis=1))
    gaps = np.concatenate(gaps)
    # the same corners as detectBoard's own refinement finds, to its 0.1 px stopping accuracy
    assert np.median(gaps) < 0.03 and gaps.max() < 0.15


def test_a_board_that_moves_further_than_tracking_reaches_is_detected_afresh(recordings_dir: Path) -> None:
    spec = SETTLED
    detector = CharucoBoardDetector(spec)
    grey = _demo_grey(recordings_dir, 0)
    first = detector.detect(grey)
    rng = np.random.default_rng(2)
    assert detector.track(_shifted(grey, 1.2, -0.8, rng), first) is not None
    assert detector.track(_shifted(grey, 6.0, 0.0, rng), first) is None  # past TRACK_MAX_SHIFT_PX
    assert detector.track(_demo_grey(recordings_dir, 60), first) is None  # another pose altogether


def _grid_detection(corners: np.ndarray) -> Detection:
    ids = np.arange(len(corners), dtype=np.int32)
    return Detection(corners.astype(np.float32), ids, np.zeros((len(corners), 3), np.float32), ids)


def test_a_held_boards_rigidity_test_allows_for_its_corner_noise_but_not_for_a_pulled_corner() -> None:
    # 70 corners 50 px apart; the next frame the board moved rigidly by (1.1, -0.6) px. Each frame's
    # corners carry their own noise: 0.15 px per coordinate on dim footage, 0.03 on a sharp board.
    rng = np.random.default_rng(0)
    grid = np.stack(np.meshgrid(np.arange(10) * 50.0 + 300, np.arange(7) * 50.0 + 200), axis=-1).reshape(-1, 2)
    move = np.array([1.1, -0.6])

    def pair(noise_px: float, pull_px: float = 0.0) -> tuple[Detection, Detection]:
        after = grid + move + rng.normal(0, noise_px, grid.shape)
        after[33] += (pull_px, 0.0)  # one corner pulled toward a marker's edge
        return _grid_detection(grid + rng.normal(0, noise_px, grid.shape)), _grid_detection(after)

    # dim footage: the noise alone puts the worst corner past the 0.5 px floor in most frames...
    worst = []
    for _ in range(40):
        before, after = pair(0.15)
        design = np.column_stack([before.corners_px, np.ones(70)])
        fit, *_ = np.linalg.lstsq(design, after.corners_px, rcond=None)
        worst.append(np.linalg.norm(design @ fit - after.corners_px, axis=1).max())
        shift = detector_module._shift_from(before, after)  # ...yet every frame is one rigid move
        assert shift is not None and np.allclose(shift, move, atol=0.1)
    assert np.mean(np.array(worst) > detector_module.TRACK_MAX_SPREAD_PX) > 0.5
    # a corner pulled 1.5 px stands out at that noise, and 0.6 px on a sharp board (the floor)
    assert detector_module._shift_from(*pair(0.15, pull_px=1.5)) is None
    assert detector_module._shift_from(*pair(0.03, pull_px=0.6)) is None
    assert detector_module._shift_from(*pair(0.03)) is not None
    # with a handful of corners the affine map absorbs much of a pull and spreads it over the rest,
    # whose median would then excuse it (a 1.5 px pull among 8 corners refused 3 times in 200): their
    # noise is not read off them
    few = [33, 34, 35, 43, 44, 45, 53, 54]
    refused = 0
    for _ in range(20):
        before, after = pair(0.1, pull_px=1.5)
        refused += detector_module._shift_from(*(_grid_detection(d.corners_px[few]) for d in (before, after))) is None
    assert refused >= 18


def test_where_a_tracked_corner_stops_depends_on_the_refinements_stopping_step(recordings_dir: Path) -> None:
    # OpenCV's 0.1 px step leaves a tracked corner near where the previous frame's markers started it
    # (bench/corner_refinement.py); a finer step lets it settle where a fresh detection's does.
    grey = _demo_grey(recordings_dir, 0)
    moved = _shifted(grey, 1.2, -0.8, np.random.default_rng(5))
    gaps = {}
    for accuracy in (0.1, 0.001):
        detector = CharucoBoardDetector(SETTLED, corner_accuracy_px=accuracy)
        tracked, fresh = detector.track(moved, detector.detect(grey)), detector.detect(moved)
        _shared, ia, ib = np.intersect1d(tracked.ids, fresh.ids, return_indices=True)
        gaps[accuracy] = float(np.median(np.linalg.norm(tracked.corners_px[ia] - fresh.corners_px[ib], axis=1)))
    assert gaps[0.001] < 0.002 < gaps[0.1] < 0.1


def test_a_change_of_view_is_detected_in_full_where_it_happens(recordings_dir: Path, tmp_path: Path) -> None:
    folder = _write(tmp_path / "two", _hold(recordings_dir, 0, 9, seed=3) + _hold(recordings_dir, 30, 9, seed=4))
    spec = SETTLED
    seen = list(HeldFrameScan(iter(ImageFolderSource(folder)), lambda: CharucoBoardDetector(spec)))
    assert [s.frame.index for s in seen if s.tracked_from is None] == sorted({9, *range(0, 18, REDETECT_EVERY)})  # the change, and the grid
    assert not any(s.in_transit for s in seen)  # one change between two holds is not a transit


def test_a_fast_transit_of_footage_is_sampled_and_never_used(recordings_dir: Path, tmp_path: Path) -> None:
    # 10 held frames (footage, by their likeness), then the board sweeps 40 px a frame for 12 frames
    grey = _demo_grey(recordings_dir, 0)
    rng = np.random.default_rng(5)
    sweep = [_shifted(grey, 40.0 * (k + 1), 0.0, rng) for k in range(12)]
    folder = _write(tmp_path / "sweep", _hold(recordings_dir, 0, 10, seed=6) + sweep + _hold(recordings_dir, 0, 6, seed=7))
    spec = SETTLED
    scan = HeldFrameScan(iter(ImageFolderSource(folder)), lambda: CharucoBoardDetector(spec))
    seen = list(scan)
    transit = [s.frame.index for s in seen if s.in_transit]
    assert transit == list(range(10, 22))  # every frame of the sweep, none of the holds
    detected_in_transit = [s.frame.index for s in seen if s.in_transit and not s.skipped]
    # a board was seen (the hold): of a transit only its first and last frames (the neighbours of the
    # holds' frames, whose speeds they give) and every 32nd frame (here none) are detected
    assert detected_in_transit == [10, 21] and not [i for i in transit if i % _TRANSIT_SAMPLE_ONCE_SEEN == 0]
    assert all(s.detection.corner_count >= 6 for s in seen if s.frame.index in (10, 21))
    assert scan.skipped == len(transit) - len(detected_in_transit)
    # the same frames are in transit when every frame is detected (--every-frame), so both reject them alike
    dense = list(HeldFrameScan(iter(ImageFolderSource(folder)), lambda: CharucoBoardDetector(spec), track=False))
    assert [s.frame.index for s in dense if s.in_transit] == transit
    assert not any(s.skipped or s.tracked_from is not None for s in dense)


def test_a_board_found_again_nearby_shows_footage_where_its_tremor_hides_the_likeness(recordings_dir: Path, tmp_path: Path,
                                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    # A fast-swinging hand: the board shakes 6 px a frame (past `_TRACKABLE_CHANGE`: no two frames
    # alike), then sweeps 40 px a frame. Found again a few px from where it was, frame after frame,
    # the board shows the source to be footage, so the sweep is a transit; taken for independent
    # stills (as before the board counted), every frame of it would be detected and judged.
    grey = _demo_grey(recordings_dir, 0)
    rng = np.random.default_rng(9)
    shaky = [_shifted(grey, 6.0 * (k % 2), 6.0 * (k // 2 % 2), rng) for k in range(10)]
    sweep = [_shifted(grey, 40.0 * (k + 1), 0.0, rng) for k in range(12)]
    folder = _write(tmp_path / "shaky", shaky + sweep)
    changes = [scan.scene_change(thumbnail(a), thumbnail(b)) for a, b in zip(shaky, shaky[1:], strict=False)]
    assert min(changes) > scan._TRACKABLE_CHANGE  # nothing alike: only the board can tell
    seen = list(HeldFrameScan(iter(ImageFolderSource(folder)), lambda: CharucoBoardDetector(SETTLED), lookahead=2))
    assert [s.frame.index for s in seen if s.in_transit] == list(range(10, 22))
    assert not any(s.tracked_from is not None for s in seen[:10])  # each shaken frame detected in full
    # detected: the sweep's first frame, beside the shaken ones (its last ends the footage: nothing beside it is judged)
    assert [s.frame.index for s in seen[10:] if not s.skipped] == [10]
    # no evidence from the board: the same frames are all detected and judged
    monkeypatch.setattr(scan, "_FOOTAGE_SHIFT", -1.0)
    blind = list(HeldFrameScan(iter(ImageFolderSource(folder)), lambda: CharucoBoardDetector(SETTLED), lookahead=2))
    assert not any(s.in_transit or s.skipped for s in blind)


def test_a_transit_before_any_board_was_seen_is_sampled_every_8th_frame(recordings_dir: Path, tmp_path: Path) -> None:
    # Footage whose board only ever moves must still show its board (the session then says "hold it
    # still" instead of looking for a wrong board spec): until a board has been seen, every 8th frame
    # of a transit is detected; after, every 32nd. An empty scene (10 frames), then the board sweeping
    # 40 px a frame out and back for 36 frames.
    grey = _demo_grey(recordings_dir, 0)
    rng = np.random.default_rng(8)
    empty = [np.clip(np.full_like(grey, 120) + rng.normal(0, 1.0, grey.shape), 0, 255).astype(np.uint8) for _ in range(10)]
    offsets = [40.0 * (k + 1) if k < 12 else 480.0 - 40.0 * (k - 11) for k in range(36)]
    sweep = [_shifted(grey, dx, 0.0, rng) for dx in offsets]
    sweep[0] = cv2.GaussianBlur(sweep[0], (0, 0), 12.0)  # the sweep's first frame, beside the empty scene: no board readable
    folder = _write(tmp_path / "sweep", empty + sweep)
    spec = SETTLED
    seen = list(HeldFrameScan(iter(ImageFolderSource(folder)), lambda: CharucoBoardDetector(spec)))
    transit = [s.frame.index for s in seen if s.in_transit]
    assert transit == list(range(10, 46))  # the whole sweep
    detected = [s for s in seen if s.in_transit and not s.skipped]
    assert detected[0].frame.index == 10 and detected[0].detection.corner_count == 0  # the transit's edge, always detected
    first_board = next(s.frame.index for s in detected if s.detection.corner_count >= 6)
    expected = [10] + [i for i in transit if i % _TRANSIT_SAMPLE == 0 and i <= first_board]
    expected += [i for i in transit if i % _TRANSIT_SAMPLE_ONCE_SEEN == 0 and i > first_board]
    assert [s.frame.index for s in detected] == expected
    assert first_board == 16 and expected == [10, 16, 32]  # 24 and 40 skipped once the board was seen at 16


def test_independent_stills_are_all_detected(shared_data: Path) -> None:
    spec = BoardSpec(20, 20, 4.0, 3.2, "DICT_4X4_1000")
    source = ImageFolderSource(shared_data / "pycamset_charuco_3cam" / "2")
    seen = list(detected_frames(source, spec))
    assert len(seen) == len(list(ImageFolderSource(shared_data / "pycamset_charuco_3cam" / "2")))
    assert not any(s.tracked_from is not None or s.in_transit or s.skipped for s in seen)


def test_slow_footage_has_no_transits_since_its_moves_do_not_smear(shared_data: Path) -> None:
    # A webcam video at 6 fps: its boards move 2-19 px from frame to frame, past the transit change
    # on 14 of 48 frames, yet at that rate such a move smears under a pixel in a webcam's exposure.
    root = shared_data / "caliscope_webcam_charuco_4x5"
    seen = list(detected_frames(open_source(root / "video" / "cam_0.mp4"), BoardSpec.from_toml(root / "charuco.toml")))
    assert len(seen) == 48 and not any(s.in_transit or s.skipped for s in seen)
    assert sum(s.detection.corner_count >= 6 for s in seen) >= 40  # each judged on its own
    # the premise by size and rate: 720p from ~23 fps, 1080p from ~16 fps (a folder: its nominal 30 fps)
    assert scan.transit_smears(1280, 30.0) and scan.transit_smears(1280, 25.0) and scan.transit_smears(1280, None)
    assert not scan.transit_smears(1280, 20.0) and not scan.transit_smears(1280, 6.0)
    assert scan.transit_smears(1920, 20.0) and not scan.transit_smears(1920, 15.0)


def _held_folder(recordings_dir: Path, tmp_path: Path, views: list[int], hold: int) -> Path:
    greys: list[np.ndarray] = []
    for k, view in enumerate(views):
        greys += _hold(recordings_dir, view, hold, seed=10 + k)
    return _write(tmp_path / "held", greys)


def test_tracked_frames_of_usable_holds_join_the_final_solve(recordings_dir: Path, tmp_path: Path) -> None:
    folder = _held_folder(recordings_dir, tmp_path, [0, 30, 66, 114, 72, 102], hold=16)
    settings = SessionSettings(selector=SelectorSettings(max_frames=6), stop_when_done=False)
    session, stats = run_replay(ImageFolderSource(folder), BoardSpec(), settings)
    dense, dense_stats = run_replay(ImageFolderSource(folder), BoardSpec(), settings, every_frame=True)
    assert stats.frames_read == dense_stats.frames_read == 96
    # all but the re-detection grid and each hold's first frame (6 holds of 16)
    assert stats.tracked >= 96 - len(range(0, 96, REDETECT_EVERY)) - 6 and dense_stats.tracked == 0
    assert session.frames_seen == dense.frames_seen == 96
    result, dense_result = session.finish(), dense.finish()
    tracked_in = [v for v in result.calibration.views if v.frame_index % 16 not in (0, 15)]
    assert len(result.calibration.views) >= 80 and len(tracked_in) >= 70  # the holds' repeats average their noise
    # the same calibration as detecting every frame afresh, within its own uncertainty, and as well fitted
    fx, dense_fx = result.calibration.camera.fx, dense_result.calibration.camera.fx
    assert abs(fx - dense_fx) < 2 * dense_result.calibration.intrinsic_std[0]
    assert abs(result.calibration.rms_px / dense_result.calibration.rms_px - 1) < 0.1


def test_held_repeats_refine_their_corners_with_the_blur_measured_on_their_hold(recordings_dir: Path, tmp_path: Path,
                                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    # Measuring each repeat's own edge blur took ~40% of a replay's session CPU; a held board's
    # blur is its judged frame's, so only judged frames (and repeats whose stillness is in doubt) are measured.
    from calibcoach.app import session_finish

    measured_for_views: list[int] = []
    measure = session_finish.edge_blur

    def counted(grey, corners, object_points):  # noqa: ANN001 - edge_blur's signature
        measured_for_views.append(len(corners))
        return measure(grey, corners, object_points)

    monkeypatch.setattr(session_finish, "edge_blur", counted)
    folder = _held_folder(recordings_dir, tmp_path, [0, 30, 66], hold=16)
    settings = SessionSettings(selector=SelectorSettings(max_frames=6), stop_when_done=False)
    session, stats = run_replay(ImageFolderSource(folder), BoardSpec(), settings)
    repeats = [v for v, _q in session._reserve if v.frame_index % REDETECT_EVERY and v.frame_index % 16]
    assert stats.tracked >= 30 and len(repeats) >= 25
    assert all(v.refined_px is not None for v in repeats)  # refined, as every view of an ordinary lens
    assert measured_for_views == []  # ... with the hold's blur: no repeat measured its own


def _jittered_folder(recordings_dir: Path, folder: Path, views: list[int], hold: int, *, smear_px: int) -> Path:
    """1080p holds whose board jumps 2 px every frame (a shaky hand at a short exposure: no smear
    within it) or, with `smear_px`, whose frames between the first and last of each hold are also
    smeared that far along the jump (the same jitter at a long exposure)."""
    rng = np.random.default_rng(7)
    smear = np.full((1, max(smear_px, 1)), 1.0 / max(smear_px, 1), np.float32)
    greys: list[np.ndarray] = []
    for view in views:
        # at 1080p a 2 px jump stays below the scan's trackable thumbnail change (24 px cells)
        grey = cv2.resize(_demo_grey(recordings_dir, view), (1920, 1080), interpolation=cv2.INTER_CUBIC)
        frames = [_shifted(grey, 2.0 * (k % 2), 0.0, rng) for k in range(hold)]
        if smear_px:
            frames = [frames[0]] + [cv2.filter2D(f, -1, smear) for f in frames[1:-1]] + [frames[-1]]
        greys += frames
    return _write(folder, greys)


def test_tracked_frames_that_moved_are_judged_by_their_own_image(recordings_dir: Path, tmp_path: Path) -> None:
    # 2 px between frames is past the 1.5 px the board may smear, so it could have smeared; whether it
    # did is read from each frame's edges, as --every-frame reads it (a 104 deg 1080p lens at 20 fps
    # lost half of its still frames when the move alone decided). No motion gate: the edges alone decide.
    settings = SessionSettings(selector=SelectorSettings(max_frames=6), stop_when_done=False, use_motion_gate=False)
    views = [0, 30, 66, 114, 72, 102]
    used = {}
    for smear_px in (0, 5):
        folder = _jittered_folder(recordings_dir, tmp_path / f"smear{smear_px}", views, 16, smear_px=smear_px)
        session, stats = run_replay(ImageFolderSource(folder), BoardSpec(), settings)
        assert stats.tracked >= 60
        result = session.finish()
        used[smear_px] = [v.frame_index for v in result.calibration.views if v.frame_index % 16 not in (0, 15)]
    assert len(used[0]) >= 60  # sharp despite the jumps: they average each pose's noise
    assert used[5] == []  # smeared: never in the solve


def test_a_glimpse_of_the_board_between_empty_frames_is_judged_by_its_own_image(recordings_dir: Path, tmp_path: Path) -> None:
    # Footage with a motion gate: after a first hold (frames 0-4) and empty frames, the board comes
    # into view at frame 10 (fully detected, rejected as just come into view), is held for frames
    # 11-12 (tracked) and is gone at frame 13 (no board). Neither judged frame around the glimpse was
    # usable, yet neither says its held frames are unsharp: their own images decide, as with every
    # frame judged (a messy capture's two-frame glimpse kept its second frame with --every-frame,
    # for 9.4% of the coverage).
    rng = np.random.default_rng(3)
    empty = [np.clip(rng.normal(120, 2.0, (720, 1280)), 0, 255).astype(np.uint8) for _ in range(5)]
    glimpse = _hold(recordings_dir, 0, 5, seed=4) + empty + _hold(recordings_dir, 30, 3, seed=5) + empty[:4]
    folder = _write(tmp_path / "glimpse", glimpse)
    settings = SessionSettings(stop_when_done=False, use_motion_gate=True)
    seen = {}
    session, _stats = run_replay(ImageFolderSource(folder), BoardSpec(), settings,
                                 on_outcome=lambda o, f: seen.__setitem__(f.index, o.decision))
    assert seen[10].reason == "moving" and seen[10].detail == "board just came into view"
    assert seen[13].reason == "no board" and 11 not in seen and 12 not in seen  # tracked, not judged
    assert {11, 12} <= {v.frame_index for v, _q in session._reserve}


@pytest.mark.parametrize("workers", [1, 2])
def test_what_is_tracked_does_not_depend_on_the_number_of_workers(recordings_dir: Path, tmp_path: Path, workers: int) -> None:
    folder = _held_folder(recordings_dir, tmp_path, [0, 30, 66], hold=12)
    runs = []
    for w in (workers, 2):
        seen = list(detected_frames(ImageFolderSource(folder), BoardSpec(), workers=w))
        runs.append([(s.frame.index, s.tracked_from, s.in_transit, s.detection.corners_px.tobytes()) for s in seen])
    assert runs[0] == runs[1]


def test_a_final_solve_that_cannot_start_with_the_repeats_falls_back_and_says_so(
        recordings_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # cv2.fisheye.calibrate sometimes cannot initialise among hundreds of frames (1 of 5 fisheye
    # renders); such a failure is injected here for any solve that holds the repeats.
    from calibcoach.app import session_finish
    from calibcoach.drivers.errors import CalibrationError

    folder = _held_folder(recordings_dir, tmp_path, [0, 30, 66, 114, 72, 102], hold=16)
    settings = SessionSettings(selector=SelectorSettings(max_frames=6), stop_when_done=False)
    session, _stats = run_replay(ImageFolderSource(folder), BoardSpec(), settings)
    real = session_finish.robust_calibrate

    def cannot_start_with_repeats(views, *args, **kwargs):
        if len(views) > 20:
            raise CalibrationError("the fisheye solve cannot initialise a view")
        return real(views, *args, **kwargs)

    monkeypatch.setattr(session_finish, "robust_calibrate", cannot_start_with_repeats)
    result = session.finish()
    assert 3 <= len(result.calibration.views) <= 20  # the distinct poses (or the live-kept frames)
    assert any("could not start with all" in reason for reason in result.verdict.reasons)


def test_a_final_solve_started_on_a_model_not_chosen_is_discarded(
        recordings_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # The robust solve of the likely model runs beside the model choice (app/session_finish.py); when
    # another model wins, the chosen one is solved and the result is the one solving after the choice gives.
    from calibcoach.app import session_finish

    folder = _held_folder(recordings_dir, tmp_path, [0, 30, 66, 114, 72, 102], hold=8)
    settings = SessionSettings(selector=SelectorSettings(max_frames=6), stop_when_done=False)
    real_choose, real_robust = session_finish.choose_model, session_finish.robust_calibrate
    solved_models = []

    def logged_robust(views, image_size, model, **kwargs):
        solved_models.append(model)
        return real_robust(views, image_size, model, **kwargs)

    monkeypatch.setattr(session_finish, "robust_calibrate", logged_robust)
    results = {}
    for told in (None, "rational"):
        def choose(views, image_size, *, on_likely=None, warm=None, told=told):
            return real_choose(views, image_size, on_likely=on_likely if told is None else (lambda _m: on_likely(told)),
                               warm=warm)

        monkeypatch.setattr(session_finish, "choose_model", choose)
        session, _stats = run_replay(ImageFolderSource(folder), BoardSpec(), settings)
        solved_models.clear()
        results[told] = session.finish().calibration
        assert sorted(solved_models) == (["pinhole"] if told is None else ["pinhole", "rational"])
    a, b = results[None], results["rational"]
    assert a.camera.model == b.camera.model == "pinhole"
    assert np.array_equal(a.camera.camera_matrix, b.camera.camera_matrix) and a.rms_px == b.rms_px
