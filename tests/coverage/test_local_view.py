"""Re-detection on a local pinhole view, on frames rendered through the 150 deg fisheye.

The hard frame is frame 3 of the sloppy seed-1 capture (30 s at 4 fps): the board far off axis
at the image edge, where plain detection finds 5 corners of the 70 in view (10 markers).
"""

from __future__ import annotations

import numpy as np
import pytest

from calibcoach.app.assistant import Assistant
from calibcoach.app.session import SessionSettings
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector, Detection
from calibcoach.coverage.local_view import hint_points, local_view_of, redetect_in_local_view
from calibcoach.coverage.redetect import Redetector
from calibcoach.drivers.geometry import pose_matrix
from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.sim import LENSES, SimulatedCamera, handheld_trajectory

FISHEYE = LENSES["fisheye150"]
SPEC = BoardSpec().with_detected(legacy=False, inverted=False)
HARD, EASY = 3, 5  # frame indices: plain detection finds 5 and 45 corners


@pytest.fixture(scope="module")
def frames() -> dict:
    trajectory = handheld_trajectory(FISHEYE, BoardSpec(), "sloppy", seconds=30, seed=1)
    poses = trajectory.sample(seconds=30, fps=4)
    source = SimulatedCamera(FISHEYE, BoardSpec(), poses, seed=1, lens_name="fisheye150", trajectory=trajectory)
    out = {}
    for i in (HARD, EASY):
        points = SPEC.corner_points_m() @ pose_matrix(poses[i].rvec).T + poses[i].tvec
        out[i] = (source.render(i), FISHEYE.project(points))
    return out


def rms_against(truth: np.ndarray, detection: Detection) -> float:
    return float(np.sqrt(np.mean(np.sum((detection.corners_px - truth[detection.ids]) ** 2, axis=1))))


def test_view_maps_back_where_the_lens_model_sends_it() -> None:
    """A view pixel and the frame pixel its map names are the same ray (the maps' interpolation is aligned)."""
    rvec, tvec = np.array([0.3, -0.6, 0.1]), np.array([0.55, 0.1, 0.45])  # board ~60 deg off axis
    board = SPEC.cv_board()
    quad = np.asarray(board.getObjPoints(), np.float64).reshape(-1, 4, 3)[20]
    hint_px = FISHEYE.project(quad, rvec, tvec)
    square = SPEC.square_mm / 1000
    view = local_view_of(FISHEYE, hint_px, quad, (8 * square, 11 * square), square)
    assert view is not None
    corners_px = FISHEYE.project(SPEC.corner_points_m(), rvec, tvec)
    in_view = view.from_frame(FISHEYE, corners_px)
    w, h = view.size
    inside = np.all((in_view > 1) & (in_view < [w - 2, h - 2]), axis=1)
    assert inside.sum() >= 60  # the view covers the board from one marker's pose
    back = view.to_frame(in_view[inside])
    assert np.max(np.linalg.norm(back - corners_px[inside], axis=1)) < 0.05


def test_off_axis_fisheye_frame_recovered_with_accurate_corners(frames) -> None:
    grey, truth = frames[HARD]
    detector = CharucoBoardDetector(SPEC)
    plain = detector.detect(grey)
    assert plain.corner_count < 6 and plain.marker_ids.size >= 4
    found = redetect_in_local_view(grey, FISHEYE, detector, plain)
    assert found is not None
    assert found.detection.corner_count >= 25  # 34 measured
    assert rms_against(truth, found.detection) < 0.1  # 0.075 measured
    ids = found.detection.ids
    assert np.all(np.diff(ids) > 0)
    np.testing.assert_allclose(found.detection.object_points_m, SPEC.corner_points_m()[ids], atol=1e-6)


def test_a_rough_lens_bends_the_view_but_does_not_move_the_corners(frames) -> None:
    """Corners map back through the maps that made the view, so the model's error does not bias them."""
    grey, truth = frames[HARD]
    detector = CharucoBoardDetector(SPEC)
    K = FISHEYE.camera_matrix.copy()
    K[:2, :2] *= 1.02
    K[0, 2] += 3.0
    rough = CameraModel("fisheye", K, FISHEYE.dist_coeffs + [0.01, 0, 0, 0], FISHEYE.image_size)
    found = redetect_in_local_view(grey, rough, detector, detector.detect(grey))
    assert found is not None and found.detection.corner_count >= 18  # 25 measured
    assert rms_against(truth, found.detection) < 0.1  # 0.061 measured


def test_plain_corners_are_kept_only_where_the_view_agrees(frames) -> None:
    grey, truth = frames[HARD]
    detector = CharucoBoardDetector(SPEC)
    plain = detector.detect(grey)
    found = redetect_in_local_view(grey, FISHEYE, detector, plain)
    assert found is not None
    missing = next(i for i in range(SPEC.corner_count) if i not in set(found.detection.ids) and i not in set(plain.ids))
    obj = SPEC.corner_points_m()[missing].astype(np.float32)

    def with_extra(px: np.ndarray) -> Detection:
        return Detection(np.vstack([plain.corners_px, px.astype(np.float32)]), np.append(plain.ids, missing).astype(np.int32),
                         np.vstack([plain.object_points_m, obj]), plain.marker_ids, plain.marker_corners_px)

    square_px = np.linalg.norm(truth[1] - truth[0])
    right = redetect_in_local_view(grey, FISHEYE, detector, with_extra(truth[missing][None]))
    wrong = redetect_in_local_view(grey, FISHEYE, detector, with_extra(truth[missing][None] + [0.6 * square_px, 0]))
    assert right is not None and missing in set(right.detection.ids)
    assert wrong is not None and missing not in set(wrong.detection.ids)


def test_redetector_leaves_narrow_lenses_and_complete_frames_alone(frames) -> None:
    grey, _truth = frames[HARD]
    plain = CharucoBoardDetector(SPEC).detect(grey)
    narrow = Redetector(SPEC)
    assert narrow.improve(0, grey, plain, LENSES["webcam720"]) is plain and narrow.counts.tried == 0
    wide = Redetector(SPEC)
    easy, _ = frames[EASY]
    full = CharucoBoardDetector(SPEC).detect(easy)
    assert full.corner_count >= 40
    assert wide.improve(0, easy, full, FISHEYE) is full and wide.counts.tried == 0
    assert wide.improve(1, grey, plain, FISHEYE).corner_count >= 25
    assert (wide.counts.tried, wide.counts.recovered) == (1, 1)


def test_a_frame_without_markers_is_pointed_at_by_the_previous_frame(frames) -> None:
    """A board held still: the frame before says where to look; a frame further back says nothing."""
    grey, truth = frames[HARD]
    redetector = Redetector(SPEC)
    plain = CharucoBoardDetector(SPEC).detect(grey)
    assert redetector.improve(10, grey, plain, FISHEYE).corner_count >= 25
    nothing = Detection.empty()
    found = redetector.improve(11, grey, nothing, FISHEYE)  # as if the markers had not been read at all
    assert found.corner_count >= 25 and rms_against(truth, found) < 0.1
    assert redetector.counts.from_previous_frame == 1
    assert redetector.improve(13, grey, nothing, FISHEYE) is nothing  # frame 12 is missing: no hint


@pytest.mark.parametrize(("hfov_guess", "recovered"), [(150.0, True), (70.0, False)])
def test_assistant_redetects_with_the_sessions_lens_guess(frames, hfov_guess: float, recovered: bool) -> None:
    """Before any solve the session's field-of-view guess points the view; a 70 deg guess says: not wide."""
    hard, _ = frames[HARD]
    easy, _ = frames[EASY]
    assistant = Assistant(SPEC, FISHEYE.image_size, settings=SessionSettings(hfov_guess_deg=hfov_guess))
    assistant.feed(easy, 0)
    assistant.feed(hard, 250_000_000)
    step = assistant.feed(easy, 500_000_000)  # decides the hard frame
    assert step.frame_index == 1 and step.outcome is not None
    assert (step.outcome.detection.corner_count >= 20) is recovered
    assert assistant.redetector is not None and assistant.redetector.counts.recovered == int(recovered)


def test_hint_points_pair_marker_corners_with_the_board() -> None:
    board = SPEC.cv_board()
    quads = np.asarray(board.getObjPoints(), np.float64).reshape(-1, 4, 3)
    rvec, tvec = np.array([0.1, 0.2, 0.0]), np.array([-0.1, -0.15, 0.6])
    px = FISHEYE.project(quads[[3, 7]].reshape(-1, 3), rvec, tvec).reshape(2, 4, 2).astype(np.float32)
    hint = Detection(np.zeros((0, 2), np.float32), np.zeros(0, np.int32), np.zeros((0, 3), np.float32),
                     np.array([3, 7], np.int32), px)
    image_px, board_m = hint_points(hint, board)
    np.testing.assert_allclose(FISHEYE.project(board_m, rvec, tvec), image_px, atol=1e-3)
