"""Pose, coverage map, frame selection and guidance on exact synthetic detections (no images).

Detections are the board's corners projected through a known lens at poses placed in image space
with the simulator's `place_board`, so every expectation below is a geometric fact.
"""

from __future__ import annotations

import numpy as np
import pytest

from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.candidates import ranges_for
from calibcoach.coverage.detector import Detection
from calibcoach.coverage.grid import CoverageMap
from calibcoach.coverage.pose import estimate_pose
from calibcoach.coverage.select import FrameSelector, SelectorSettings, board_motion_px, corner_spread
from calibcoach.coverage.sharpness import EdgeBlur
from calibcoach.coverage.virtual_view import BoardGeometry
from calibcoach.drivers.lens import CameraModel

from _synthetic import detection_at as synthetic_detection

SPEC = BoardSpec()
CAMERA = CameraModel("pinhole", [[900, 0, 640], [0, 900, 360], [0, 0, 1]], [-0.1, 0.05, 0, 0, 0], (1280, 720))
W, H = CAMERA.image_size
RANGES = ranges_for(CAMERA, BoardGeometry.of(SPEC))  # near <= 0.59 m, far >= 0.79 m on this lens
CENTRE = BoardGeometry.of(SPEC).centre_m


def new_map() -> CoverageMap:
    return CoverageMap((W, H), ranges=RANGES)


def selector(**settings) -> FrameSelector:
    return FrameSelector((W, H), squares_x=SPEC.squares_x, settings=SelectorSettings(**settings), coverage=new_map())


def detection_at(centre_px, distance_m=0.9, *, tilt_x=0.0, tilt_y=0.0, keep=None) -> Detection:
    return synthetic_detection(CAMERA, centre_px, distance_m, tilt_x=tilt_x, tilt_y=tilt_y, keep=keep, spec=SPEC)


@pytest.mark.parametrize(("tilt_x", "tilt_y"), [(0, 0), (35, 0), (-35, 0), (0, 40), (0, -40)])
def test_pose_recovers_signed_tilts(tilt_x: float, tilt_y: float) -> None:
    pose = estimate_pose(detection_at((500, 300), tilt_x=tilt_x, tilt_y=tilt_y), CAMERA)
    assert pose is not None
    assert pose.tilt_x_deg == pytest.approx(tilt_x, abs=1.5)
    assert pose.tilt_y_deg == pytest.approx(tilt_y, abs=1.5)
    assert pose.tilt_deg == pytest.approx(max(abs(tilt_x), abs(tilt_y)), abs=1.5)
    assert pose.fit_rms_px < 0.01  # float32 corners


def test_compound_tilt_keeps_both_signs() -> None:
    pose = estimate_pose(detection_at((500, 300), tilt_x=-30, tilt_y=30), CAMERA)
    assert pose is not None and pose.tilt_x_deg < -25 and pose.tilt_y_deg > 25 and pose.tilt_deg > 40


def test_tilt_is_measured_against_the_line_of_sight() -> None:
    # a board held facing the camera in the image corner is frontal, although it is not parallel to the sensor
    pose = estimate_pose(detection_at((200, 120), 1.2), CAMERA)
    assert pose is not None and pose.tilt_deg < 1.0


def test_footprint_shrinks_with_distance() -> None:
    near = estimate_pose(detection_at((640, 360), 0.6), CAMERA)
    far = estimate_pose(detection_at((640, 360), 1.6), CAMERA)
    assert near is not None and far is not None
    assert far.footprint == pytest.approx(near.footprint * 0.6 / 1.6, rel=0.05)
    assert far.distance_m == pytest.approx(1.6, rel=0.02)


def test_range_is_the_board_centres_distance_even_when_most_of_the_board_is_out_of_view() -> None:
    # the board centred on the image corner shows about a quarter of its corners: its footprint is
    # small, but the person holds it near, and the map must say so (issue 9: distance from the pose)
    partial = detection_at((0, 0), 0.5)
    assert 6 <= partial.corner_count < 30
    pose = estimate_pose(partial, CAMERA, CENTRE)
    assert pose is not None and pose.distance_m == pytest.approx(0.5, rel=0.02)
    assert pose.footprint < 0.3
    assert new_map().contribution(partial, pose).distance_cell == "near"


def test_coverage_counts_corners_where_they_land_and_credits_tilt_and_distance() -> None:
    cmap = new_map()
    assert (cmap.rows, cmap.cols) == (4, 6)
    det = detection_at((150, 100), 1.2, tilt_x=40)
    c = cmap.contribution(det, estimate_pose(det, CAMERA, CENTRE))
    assert c.region_counts[0, 0] > 0 and c.region_counts[-1, -1] == 0
    assert set(c.tilt_cells) == {"top_away", "steep_x"}
    assert c.distance_cell == "far"
    before = cmap.completeness()
    gain = cmap.gain(c)
    cmap.add(c)
    assert cmap.completeness() == pytest.approx(before + gain)
    assert cmap.gain(c) < gain  # the same frame again adds less


def test_a_diverse_capture_completes_the_map_and_frontal_centred_frames_never_do() -> None:
    diverse = new_map()
    frontal = new_map()
    xs, ys = np.linspace(120, W - 120, 6), np.linspace(100, H - 100, 4)
    tilts = [(0, 0), (35, 0), (-35, 0), (0, 40), (0, -40), (25, 25)]
    for i, (x, y) in enumerate((x, y) for y in ys for x in xs):
        for dist in (0.45, 0.7, 1.0):
            tx, ty = tilts[(i + int(dist * 10)) % len(tilts)]
            det = detection_at((x, y), dist, tilt_x=tx, tilt_y=ty)
            if det.corner_count >= 6:
                diverse.add(diverse.contribution(det, estimate_pose(det, CAMERA, CENTRE)))
    for k in range(40):
        det = detection_at((640 + 10 * np.sin(k), 360 + 8 * np.cos(k)), 0.9, tilt_x=3 * np.sin(k))
        frontal.add(frontal.contribution(det, estimate_pose(det, CAMERA, CENTRE)))
    assert diverse.is_complete(), diverse.summary()["missing"]
    assert not frontal.is_complete()
    assert frontal.completeness() < 0.6
    assert frontal.missing_tilts() == ["top_away", "bottom_away", "left_away", "right_away", "steep_x", "steep_y"]
    assert (0, 0) in [(r, c) for r, c, _ in frontal.missing_regions()]


def test_unreachable_regions_are_not_required() -> None:
    reachable = np.ones((4, 6), bool)
    reachable[0, 0] = reachable[-1, -1] = False  # e.g. a fisheye's black corners
    cmap = CoverageMap((W, H), ranges=RANGES, reachable=reachable)
    assert (0, 0) not in [(r, c) for r, c, _ in cmap.missing_regions()]
    assert cmap.region_weights[0, 0] == 0 and cmap.region_weights.sum() == pytest.approx(1.0)
    assert cmap.region_met()[0, 0] and not cmap.region_met()[0, 1]
    # an uncertainty grid's points fall in the cells they lie in (cells are 213.3 x 180 px at 1280 x 720)
    x = np.array([0.0, 213.0, 214.0, 1279.0])
    y = np.array([0.0, 179.0, 181.0, 719.0])
    at = cmap.reachable_at(x, y)
    assert at.shape == (4, 4)
    assert not at[0, 0] and not at[1, 1] and at[0, 2] and at[2, 1] and not at[3, 3] and at[3, 2]


def test_selector_gates_each_reason() -> None:
    sel = selector()
    full = detection_at((640, 360), 0.9)
    few = Detection(full.corners_px[:5], full.ids[:5], full.object_points_m[:5], full.marker_ids)
    row = full.ids < 7  # one board row: collinear
    line = Detection(full.corners_px[row], full.ids[row], full.object_points_m[row], full.marker_ids)
    # five corners down one column and one beside it: a pose OpenCV's solver cannot pin down
    column = np.isin(full.ids, [6, 13, 20, 27, 34, 33])
    l_shape = Detection(full.corners_px[column], full.ids[column], full.object_points_m[column], full.marker_ids)
    assert sel.gate(Detection.empty()).reason == "no board"
    assert sel.gate(few).reason == "too few corners"
    assert corner_spread(line) < 0.01
    assert sel.gate(line).reason == "collinear"
    assert sel.gate(l_shape).reason == "collinear"
    assert sel.gate(full) is None
    pose = estimate_pose(full, CAMERA)
    moving, _ = sel.decide(0, full, pose, motion_px_s=80.0, blur_px=1.0)
    assert moving.reason == "moving" and moving.quality == 0.0  # no smear measured: the speed decides
    smeared, _ = sel.decide(0, full, pose, motion_px_s=5.0, blur_px=0.8, edges=EdgeBlur(0.8, 1.05))
    assert smeared.reason == "moving" and "smeared 2.4 px" in smeared.detail and smeared.quality == 0.0
    assert sel.decide(0, full, pose, motion_px_s=5.0, blur_px=1.0)[0].accepted
    blurred, _ = sel.decide(0, full, pose, motion_px_s=None, blur_px=3.5)
    assert blurred.reason == "blurred" and blurred.quality == 0.0


def test_a_jittering_but_unsmeared_board_is_still_once_the_cameras_sharpness_is_known() -> None:
    sel = selector()
    for k, x in enumerate((300, 640, 980)):
        det = detection_at((x, 360), 0.9)
        d, c = sel.decide(k, det, estimate_pose(det, CAMERA, CENTRE), motion_px_s=None, blur_px=0.8, edges=EdgeBlur(0.8, 0.82))
        sel.commit(k, det, estimate_pose(det, CAMERA, CENTRE), c, blur_px=0.8)
    assert sel.own_sharpness_px() == pytest.approx(0.8)
    # 2 px of jitter per frame at 30 fps is 60 px/s: the frame itself shows no smear, so it is still
    det = detection_at((200, 130), 1.0, tilt_y=30)
    d, _ = sel.decide(9, det, estimate_pose(det, CAMERA, CENTRE), motion_px_s=60.0, blur_px=0.83, edges=EdgeBlur(0.83, 0.86))
    assert d.accepted, d
    # the same speed with both edge families widened beyond the camera's own: a smear along a diagonal
    d, _ = sel.decide(10, det, estimate_pose(det, CAMERA, CENTRE), motion_px_s=60.0, blur_px=1.0, edges=EdgeBlur(1.0, 1.0))
    assert d.reason == "moving" and "diagonal" in d.detail


def test_selector_accepts_new_coverage_and_rejects_look_alikes() -> None:
    sel = selector()
    first = detection_at((640, 360), 0.9)
    d1, c1 = sel.decide(0, first, estimate_pose(first, CAMERA), motion_px_s=None, blur_px=1.0)
    assert d1.accepted and c1 is not None
    sel.commit(0, first, estimate_pose(first, CAMERA), c1, blur_px=1.0)
    twin = detection_at((646, 357), 0.91)
    d2, _ = sel.decide(1, twin, estimate_pose(twin, CAMERA), motion_px_s=None, blur_px=1.0)
    assert d2.reason == "duplicate" and "frame 0" in d2.detail
    # never kept live, however much it would cut the error: a repeat weights one pose over the rest
    d3, _ = sel.decide(1, twin, estimate_pose(twin, CAMERA), motion_px_s=None, blur_px=1.0,
                       uncertainty_gain=lambda: 0.9, uncertainty_needed=0.01)
    assert d3.reason == "duplicate" and d3.quality > 0  # held in reserve for the final solve
    corner = detection_at((200, 130), 1.2, tilt_y=40)
    d4, _ = sel.decide(2, corner, estimate_pose(corner, CAMERA), motion_px_s=None, blur_px=1.0)
    assert d4.accepted and d4.coverage_gain > 0.02


def test_selector_blur_limit_follows_the_cameras_own_sharpness() -> None:
    sel = selector(keep_all_usable=True)
    for k in range(3):
        det = detection_at((300 + 200 * k, 360), 0.9)
        d, c = sel.decide(k, det, estimate_pose(det, CAMERA, CENTRE), motion_px_s=None, blur_px=0.8)
        sel.commit(k, det, estimate_pose(det, CAMERA, CENTRE), c, blur_px=0.8)
    det = detection_at((640, 200), 0.9)
    d, _ = sel.decide(9, det, estimate_pose(det, CAMERA, CENTRE), motion_px_s=None, blur_px=1.8)
    assert d.reason == "blurred" and "limit 1.6" in d.detail
    assert d.quality == pytest.approx((1.6 / 1.8) ** 2)  # kept in reserve at a lower weight


def test_frame_limit() -> None:
    sel = selector(max_frames=1, keep_all_usable=True)
    det = detection_at((640, 360), 0.9)
    d, c = sel.decide(0, det, None, motion_px_s=None, blur_px=None)
    sel.commit(0, det, None, c)
    assert sel.decide(1, det, None, motion_px_s=None, blur_px=None)[0].reason == "frame limit"


def test_board_motion_uses_shared_corners_only() -> None:
    a = detection_at((640, 360), 0.9)
    shifted = Detection(a.corners_px[5:] + [3.0, 4.0], a.ids[5:], a.object_points_m[5:], a.marker_ids)
    assert board_motion_px(a, shifted) == pytest.approx(5.0)
    assert board_motion_px(None, a) is None
