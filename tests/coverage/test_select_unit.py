"""The selector's keep/reject decisions at each of their limits, on constructed detections, and the
edge-blur measure on a synthetic chessboard smeared along a known direction.

Complements test_coverage_selection.py (which walks the gates once each): here every limit is
checked on both sides, with its reason, detail and quality.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.candidates import ranges_for
from calibcoach.coverage.detector import Detection
from calibcoach.coverage.grid import CoverageMap
from calibcoach.coverage.pose import estimate_pose
from calibcoach.coverage.select import (
    AcceptedView,
    FrameSelector,
    SelectorSettings,
    accepted_view,
    board_motion_px,
    corner_spread,
    look_alike,
    look_alike_groups,
    spans_rows_and_columns,
)
from calibcoach.coverage.sharpness import EdgeBlur, edge_blur
from calibcoach.coverage.virtual_view import BoardGeometry
from calibcoach.drivers.sim import LENSES

from _synthetic import detection_at

SPEC = BoardSpec()
CAMERA = LENSES["webcam720"]
W, H = CAMERA.image_size
DIAG = float(np.hypot(W, H))
CENTRE = BoardGeometry.of(SPEC).centre_m


def selector(size=(W, H), **settings) -> FrameSelector:
    return FrameSelector(size, squares_x=SPEC.squares_x, settings=SelectorSettings(**settings),
                         coverage=CoverageMap(size, ranges=ranges_for(CAMERA, BoardGeometry.of(SPEC))))


def seen(centre_px=(640, 360), distance_m=0.9, **kw):
    det = detection_at(CAMERA, centre_px, distance_m, spec=SPEC, **kw)
    return det, estimate_pose(det, CAMERA, CENTRE)


def subset(det: Detection, ids) -> Detection:
    keep = np.isin(det.ids, ids)
    return Detection(det.corners_px[keep], det.ids[keep], det.object_points_m[keep], det.marker_ids)


def consistent(d):
    """A decision is accepted exactly when its reason says so (a rejected frame never reaches the solve),
    and a kept frame is of full quality (the final solve takes only frames of quality 1)."""
    assert d.accepted is (d.reason == "accepted"), d
    assert not d.accepted or d.quality == 1.0, d
    return d


def unmeasured(d):
    """A frame turned away before the diversity test: no coverage or error cut was computed for it."""
    assert (d.coverage_gain, d.uncertainty_gain) == (0.0, 0.0), d
    return d


def decide(sel, det, pose, **kw):
    kw.setdefault("motion_px_s", None)
    kw.setdefault("blur_px", 1.0)
    d, contribution = sel.decide(0, det, pose, **kw)
    assert (contribution is not None) is d.accepted  # only a kept frame comes with its coverage to commit
    return consistent(d)


# --- gates 1-2 ----------------------------------------------------------------------------------


def test_six_corners_are_enough_and_five_are_not() -> None:
    sel = selector()
    det, _ = seen()
    block = [0, 1, 2, 7, 8, 9]  # two rows of three: a real area
    assert sel.gate(subset(det, block)) is None
    five = unmeasured(sel.gate(subset(det, block[:5])))
    assert (five.accepted, five.reason, five.detail, five.quality) == (False, "too few corners", "5 corners, need 6", 0.0)
    assert selector(min_corners=8).gate(subset(det, block)).detail == "6 corners, need 8"
    empty = unmeasured(consistent(sel.gate(Detection.empty())))
    assert (empty.reason, empty.detail, empty.quality) == ("no board", "0 markers", 0.0)


def test_collinear_means_one_row_one_column_or_a_thin_sliver() -> None:
    det, _ = seen()
    per_row = SPEC.squares_x - 1
    row = list(range(per_row))
    assert corner_spread(subset(det, row)) < 1e-6 and not spans_rows_and_columns(subset(det, row), SPEC.squares_x)
    column = [k * per_row for k in range(6)]
    assert not spans_rows_and_columns(subset(det, column), SPEC.squares_x)
    assert spans_rows_and_columns(subset(det, [0, 1, per_row, per_row + 1]), SPEC.squares_x)
    assert corner_spread(subset(det, [0, 1, per_row, per_row + 1])) == pytest.approx(1.0)  # a square patch
    # two full rows: spread = row spacing / row length = 1 / 6 * sqrt(3) ... below 0.25
    two_rows = subset(det, list(range(2 * per_row)))
    spread = corner_spread(two_rows)
    assert spread == pytest.approx(0.5 / np.sqrt((per_row**2 - 1) / 12), rel=1e-3)
    sel = selector()
    line = unmeasured(consistent(sel.gate(two_rows)))
    assert (line.reason, line.detail, line.quality) == ("collinear", f"spread {spread:.2f}", 0.0)
    assert consistent(sel.gate(subset(det, column))).reason == "collinear"  # one column: no area whatever the spread
    assert selector(min_spread=spread - 0.01).gate(two_rows) is None
    assert selector(min_spread=spread).gate(two_rows) is None  # "at least": the limit itself passes
    three_rows = subset(det, list(range(3 * per_row)))
    assert corner_spread(three_rows) > 0.25 and sel.gate(three_rows) is None
    assert corner_spread(subset(det, [0, 1])) == 0.0
    assert corner_spread(subset(det, [0, 1, per_row])) == pytest.approx(np.sqrt(1 / 3))  # three corners: an L has an area


# --- stillness and sharpness --------------------------------------------------------------------


def test_blur_above_the_absolute_limit_is_useless() -> None:
    det, pose = seen()
    sel = selector()
    assert decide(sel, det, pose, blur_px=3.0).accepted
    d = unmeasured(decide(sel, det, pose, blur_px=3.01))
    assert (d.reason, d.detail, d.quality) == ("blurred", "edge blur 3.0 px, limit 3.0", 0.0)


def test_a_board_that_just_came_into_view_is_moving() -> None:
    det, pose = seen()
    d = unmeasured(decide(selector(), det, pose, just_appeared=True))
    assert (d.accepted, d.reason, d.detail, d.quality) == (False, "moving", "board just came into view", 0.25)


@pytest.mark.parametrize("width", [1280, 640])
def test_transit_speed_is_a_veto_scaled_with_the_width(width: int) -> None:
    det, pose = seen()
    limit = 80.0 * width / 1280
    sel = selector(size=(width, width * 9 // 16))
    for _ in range(3):  # this camera's sharpness is known: the smear is read off the frame below the transit limit
        sel._blurs.append(1.0)
    still = EdgeBlur(1.0, 1.0)
    assert decide(sel, det, pose, motion_px_s=limit - 0.5, edges=still).reason != "moving"
    assert decide(sel, det, pose, motion_px_s=limit * 0.9995, edges=still).reason != "moving"  # exactly proportional
    d = decide(sel, det, pose, motion_px_s=limit + 0.5, edges=still)
    assert (d.reason, d.quality) == ("moving", 0.0)
    assert d.detail == f"{limit + 0.5:.0f} px/s: in transit (limit {limit:.0f})"


def test_the_speed_hint_decides_until_the_cameras_sharpness_is_known() -> None:
    det, pose = seen()
    sel = selector()
    assert decide(sel, det, pose, motion_px_s=25.0).accepted
    d = decide(sel, det, pose, motion_px_s=25.5)
    assert d.reason == "moving" and d.detail == "26 px/s, limit 25 until this camera's own sharpness is known"
    d = decide(sel, det, pose, motion_px_s=25.5, edges=EdgeBlur(1.0, 1.0))  # edges alone do not help before that
    assert d.reason == "moving" and "until this camera's own sharpness" in d.detail
    sel._blurs += [1.0, 1.0, 1.0]
    assert decide(sel, det, pose, motion_px_s=25.5, edges=EdgeBlur(1.0, 1.0)).accepted
    assert decide(sel, det, pose, motion_px_s=25.5).reason == "moving"  # no edges: still the speed
    assert decide(sel, det, pose, motion_px_s=25.5, edges=EdgeBlur(float("inf"), float("inf"))).reason == "moving"


def test_before_three_kept_frames_the_sharpest_frames_seen_give_the_cameras_sharpness() -> None:
    # a shaky hand: every frame moves faster than the hint allows, so none is kept; waiting for
    # three kept frames would leave the speed deciding for ever
    det, pose = seen()
    sel = selector(min_coverage_gain=1.0, min_uncertainty_gain=1.0)
    moving = {"motion_px_s": 40.0}
    widths = [0.8, 0.8, 0.9, 1.0, 1.1, 1.2, 1.3]
    for sharp in widths:
        d = decide(sel, det, pose, edges=EdgeBlur(sharp, sharp), **moving)
        assert d.reason == "moving" and "until this camera's own sharpness" in d.detail
    decide(sel, det, pose, edges=EdgeBlur(1.4, 1.4), **moving)  # the 8th frame with a board
    assert sel.own_sharpness_px() == pytest.approx(np.percentile([*widths, 1.4], 5))
    # from now the edges decide: as sharp as the camera is still, 35% wider while moving is smeared
    assert decide(sel, det, pose, edges=EdgeBlur(0.82, 0.82), **moving).reason == "adds nothing"
    assert decide(sel, det, pose, edges=EdgeBlur(1.2, 1.2), **moving).reason == "moving"


def test_frames_measured_outside_the_judgement_count_towards_the_cameras_sharpness() -> None:
    # a replay measures the edges of tracked frames it judges by their own image: they are frames
    # with a board seen, as judged ones are, up to the same blur limit and until three frames are kept
    sel = selector()
    for sharp in [0.8, 0.9, 1.0, 1.1, 1.2, 1.3, 1.4]:
        sel.note_sharpness(EdgeBlur(sharp, sharp))
    sel.note_sharpness(EdgeBlur(99.0, 99.0))  # past the absolute blur limit: not this camera's sharpness
    sel.note_sharpness(EdgeBlur(float("inf"), float("inf")))
    sel.note_sharpness(None)
    assert sel.own_sharpness_px() is None
    sel.note_sharpness(EdgeBlur(0.85, 0.85))  # the 8th
    assert sel.own_sharpness_px() == pytest.approx(np.percentile([0.8, 0.9, 1.0, 1.1, 1.2, 1.3, 1.4, 0.85], 5))
    sel._blurs += [1.0, 1.0, 1.0]  # three kept: their median is the camera's sharpness, nothing more is noted
    sel.note_sharpness(EdgeBlur(0.5, 0.5))
    assert sel.own_sharpness_px() == 1.0 and len(sel._seen_sharpness) == 8


def edges_with_smear(sharp: float, smear: float) -> EdgeBlur:
    """Edge widths for a smear of `smear` px along the board's x axis over a `sharp` px lens blur."""
    return EdgeBlur(sharp, float(np.sqrt(sharp**2 + smear**2 / 12.0)))


def test_a_smeared_frame_is_rejected_by_its_edges() -> None:
    det, pose = seen()
    sel = selector()
    assert decide(sel, det, pose, edges=edges_with_smear(0.8, 1.49)).accepted
    d = decide(sel, det, pose, edges=edges_with_smear(0.8, 1.6))
    assert (d.reason, d.detail, d.quality) == ("moving", "smeared 1.6 px during the exposure, limit 1.5", 0.0)
    # ...along either axis
    e = edges_with_smear(0.8, 1.6)
    assert decide(sel, det, pose, edges=EdgeBlur(e.across_y_px, e.across_x_px)).reason == "moving"
    # a soft image whose families differ by a few % reads as "smear" but widens the edges by < 15%
    soft = edges_with_smear(2.6, 3.0)
    assert soft.along_smear_px() == pytest.approx(3.0) and soft.along_widening() < 1.15
    assert decide(sel, det, pose, edges=soft, blur_px=2.7).accepted
    assert decide(selector(min_smear_widening=1.0), det, pose, edges=soft, blur_px=2.7).reason == "moving"


def test_a_diagonal_smear_needs_the_cameras_own_sharpness_and_a_moving_board() -> None:
    det, pose = seen()
    sel = selector()
    sel._blurs += [0.8, 0.8, 0.8]
    wide = EdgeBlur(1.0, 1.0)  # both families 25% wider than the camera's own 0.8 px: sqrt(24 * 0.36) = 2.9 px
    assert wide.diagonal_smear_px(0.8) == pytest.approx(np.sqrt(24 * 0.36))
    d = decide(sel, det, pose, motion_px_s=30.0, edges=wide)
    assert d.reason == "moving" and d.detail == "smeared 2.9 px along a board diagonal, limit 1.5 (30 px/s)"
    assert d.quality == 0.0 and not d.accepted  # smeared: never in the final solve
    assert decide(sel, det, pose, motion_px_s=20.0, edges=wide).accepted  # a still board: soft, not smeared
    slight = EdgeBlur(0.87, 0.87)  # 1.7 px by the formula, but only 9% wider: within the measure's scatter
    assert slight.diagonal_smear_px(0.8) > 1.5 and decide(sel, det, pose, motion_px_s=30.0, edges=slight).accepted


def test_blur_relative_to_the_cameras_own() -> None:
    det, pose = seen()
    sel = selector()
    assert sel.own_sharpness_px() is None and sel.blur_limit_px() == 3.0
    sel._blurs += [0.7, 0.9, 0.8]
    assert sel.own_sharpness_px() == pytest.approx(0.8) and sel.blur_limit_px() == pytest.approx(1.6)
    assert decide(sel, det, pose, blur_px=1.6).accepted
    d = decide(sel, det, pose, blur_px=2.0)
    assert d.reason == "blurred" and d.detail == "edge blur 2.0 px, limit 1.6" and d.quality == pytest.approx(0.64)
    sel._blurs += [2.5, 2.5, 2.5, 2.5]
    assert sel.blur_limit_px() == 3.0  # twice the own blur, never above the absolute limit


# --- diversity ----------------------------------------------------------------------------------


def test_a_twin_of_an_accepted_view_is_rejected() -> None:
    sel = selector()
    det, pose = seen((640, 360), 0.9)
    d, contribution = sel.decide(3, det, pose, motion_px_s=None, blur_px=1.0)
    assert d.accepted and d.reason == "accepted" and d.detail.startswith("adds ") and d.coverage_gain > 0.01
    sel.commit(3, det, pose, contribution, blur_px=1.0)
    assert sel.accepted_blurs == [1.0]
    twin, twin_pose = seen((660, 350), 0.92, tilt_x=5.0)
    d = decide(sel, twin, twin_pose)
    assert (d.accepted, d.reason, d.detail, d.quality) == (False, "duplicate", "looks like frame 3", 1.0)
    other, other_pose = seen((640, 360), 0.9, tilt_y=20.0)  # same place, tilted: a new view
    assert decide(sel, other, other_pose).reason != "duplicate"
    d = decide(sel, twin, None)  # without a pose there is no look-alike test
    assert d.reason != "duplicate"


def view(x=0.0, y=0.0, footprint=0.3, tx=0.0, ty=0.0) -> AcceptedView:
    return AcceptedView(0, np.array([x, y]), footprint, tx, ty)


@pytest.mark.parametrize(("change", "alike"), [
    ({"x": 0.0599 * DIAG}, True), ({"x": 0.0601 * DIAG}, False),
    ({"y": 0.0599 * DIAG}, True), ({"y": 0.0601 * DIAG}, False),
    ({"footprint": 0.3 - 0.0449}, True), ({"footprint": 0.3 - 0.0451}, False),  # 15% of the first frame's
    ({"footprint": 0.3 + 0.0449}, True), ({"footprint": 0.3 + 0.0451}, False),
    ({"tx": 7.99}, True), ({"tx": 8.01}, False), ({"tx": -8.01}, False),
    ({"ty": 7.99}, True), ({"ty": 8.01}, False), ({"ty": -7.99}, True),
])
def test_look_alike_limits(change: dict, alike: bool) -> None:
    settings = SelectorSettings()
    assert look_alike(view(), view(**change), settings, DIAG) is alike  # (kept frame, new frame)
    if "footprint" not in change:
        assert look_alike(view(**change), view(), settings, DIAG) is alike


def test_look_alike_compares_tilt_differences_whatever_the_tilts() -> None:
    s = SelectorSettings()
    assert look_alike(view(tx=20.0, ty=-20.0), view(tx=25.0, ty=-15.0), s, DIAG)  # both tilted alike
    assert not look_alike(view(tx=-4.5, ty=0.0), view(tx=4.5, ty=0.0), s, DIAG)  # tilted opposite ways: 9 deg apart
    assert not look_alike(view(tx=0.0, ty=4.5), view(tx=0.0, ty=-4.5), s, DIAG)


def test_look_alike_groups_are_transitive_in_order() -> None:
    s = SelectorSettings()
    step = 0.04 * DIAG  # each alike its neighbour, the ends not alike each other
    looks = [view(x=0), view(x=step), view(x=2 * step), None, view(x=10 * step), view(x=10 * step + 1)]
    assert not look_alike(looks[0], looks[2], s, DIAG)
    assert look_alike_groups(looks, s, DIAG) == [0, 0, 0, 3, 4, 4]


def test_accepted_view_is_centroid_footprint_and_tilts() -> None:
    det, pose = seen((500, 300), 0.8, tilt_x=20)
    av = accepted_view(7, det, pose)
    assert av.frame_index == 7 and av.footprint == pose.footprint and av.tilt_x_deg == pose.tilt_x_deg
    np.testing.assert_allclose(av.centre_px, det.corners_px.astype(np.float64).mean(axis=0))


def test_without_new_coverage_a_frame_must_cut_the_error() -> None:
    sel = selector(min_coverage_gain=1.0, max_frames=200)  # no frame counts as new coverage: the error cut decides
    det, pose = seen((640, 360), 0.9)
    sel.commit(0, det, pose, sel.coverage.contribution(det, pose))
    again, again_pose = seen((640, 360), 0.9, tilt_x=9.0)  # not a twin (9 deg)
    kw = {"motion_px_s": None, "blur_px": 1.0}
    d = consistent(sel.decide(1, again, again_pose, **kw)[0])
    assert d.reason == "adds nothing" and 0 < d.coverage_gain < 1.0
    assert d.detail.endswith("expected error -0.0% (needs 75.0%)")  # 1.5 / (1 kept + 1)
    cut = consistent(sel.decide(1, again, again_pose, uncertainty_gain=lambda: 0.1, uncertainty_needed=0.1, **kw)[0])
    assert cut.accepted and cut.detail == "cuts the expected error by 10%" and cut.uncertainty_gain == 0.1
    short = consistent(sel.decide(1, again, again_pose, uncertainty_gain=lambda: 0.099, uncertainty_needed=0.1, **kw)[0])
    assert short.reason == "adds nothing" and short.uncertainty_gain == 0.099
    for k in range(100):
        sel.accepted.append(view(x=5000.0 + 1000 * k))
    floor = consistent(sel.decide(1, again, again_pose, uncertainty_gain=lambda: 0.019, **kw)[0])
    assert floor.reason == "adds nothing" and "needs 2.0%" in floor.detail  # never below 2%
    assert consistent(sel.decide(1, again, again_pose, uncertainty_gain=lambda: 0.02, **kw)[0]).accepted


def test_a_frame_kept_without_a_pose_is_recorded_at_its_corner_centroid() -> None:
    sel = selector()
    det, pose = seen((500, 300), 0.8)
    sel.commit(4, det, None, sel.coverage.contribution(det, None))
    kept = sel.accepted[-1]
    np.testing.assert_allclose(kept.centre_px, det.corners_px.astype(np.float64).mean(axis=0))
    assert (kept.frame_index, kept.footprint, kept.tilt_x_deg, kept.tilt_y_deg) == (4, 0.0, 0.0, 0.0)  # no pose: nothing known


def test_keep_all_usable_and_the_frame_limit() -> None:
    sel = selector(keep_all_usable=True, max_frames=2)
    det, pose = seen()
    for k in range(2):
        d, c = sel.decide(k, det, pose, motion_px_s=None, blur_px=1.0)
        assert d.accepted and d.detail.startswith("usable photo")  # even a twin
        sel.commit(k, det, pose, c)
    d = decide(sel, det, pose)
    assert (d.reason, d.detail, d.quality) == ("frame limit", "2 frames kept already", 1.0)  # usable, just not needed
    unmeasured(d)
    sel.record(d)
    sel.record(d)
    assert sel.counts["frame limit"] == 2 and sel.counts["accepted"] == 0


def test_board_motion_needs_four_shared_corners() -> None:
    det, _ = seen()
    moved = Detection(det.corners_px + np.float32([3.0, 4.0]), det.ids, det.object_points_m, det.marker_ids)
    assert board_motion_px(subset(det, [0, 1, 2, 3]), moved) == pytest.approx(5.0)
    assert board_motion_px(subset(det, [0, 1, 2]), moved) is None  # three: too few to tell a move from a misread
    assert board_motion_px(det, Detection.empty()) is None and board_motion_px(Detection.empty(), det) is None


def test_settings_decisions_and_views_are_immutable_values() -> None:
    import dataclasses

    det, pose = seen()
    for value, field in ((SelectorSettings(), "max_frames"), (decide(selector(), det, pose), "accepted"),
                         (accepted_view(0, det, pose), "footprint")):
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(value, field, 0)


# --- the edge-blur measure ----------------------------------------------------------------------


def chessboard(smear_px: float, direction_deg: float, *, rotation_deg: float = 0.0, lens_blur_px: float = 0.8):
    """A 9 x 7 chessboard of 40 px squares, rotated, blurred by a lens and smeared by a box of
    `smear_px` along `direction_deg` (image angle). Returns (grey, corners_px, object points)."""
    sq, nx, ny, ox, oy = 40, 9, 7, 460, 220
    big = np.full((720, 1280), 235, np.float32)
    for j in range(ny):
        for i in range(nx):
            if (i + j) % 2 == 0:
                big[oy + j * sq: oy + (j + 1) * sq, ox + i * sq: ox + (i + 1) * sq] = 25
    centre = (ox + nx * sq / 2 - 0.5, oy + ny * sq / 2 - 0.5)
    R = cv2.getRotationMatrix2D(centre, rotation_deg, 1.0)
    img = cv2.warpAffine(big, R, (1280, 720), flags=cv2.INTER_LINEAR, borderValue=235)
    img = cv2.GaussianBlur(img, (0, 0), lens_blur_px)
    if smear_px > 0:
        n = int(np.ceil(smear_px)) * 2 + 1
        kernel = np.zeros((n, n), np.float32)
        c = n // 2
        d = np.array([np.cos(np.radians(direction_deg)), np.sin(np.radians(direction_deg))])
        for s in np.linspace(-smear_px / 2, smear_px / 2, 200):  # a box of length smear_px, sub-pixel
            x, y = c + s * d
            x0, y0 = int(np.floor(x)), int(np.floor(y))
            fx, fy = x - x0, y - y0
            for dx, dy, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
                kernel[y0 + dy, x0 + dx] += wgt
        img = cv2.filter2D(img, -1, kernel / kernel.sum())
    grey = np.clip(img, 0, 255).astype(np.uint8)
    gx, gy = np.meshgrid(np.arange(1, nx), np.arange(1, ny))
    grid = np.stack([ox + gx.ravel() * sq - 0.5, oy + gy.ravel() * sq - 0.5], 1)
    corners = (R[:, :2] @ grid.T).T + R[:, 2]
    obj = np.concatenate([np.stack([gx.ravel(), gy.ravel()], 1) * 0.03, np.zeros((grid.shape[0], 1))], 1)
    return grey, corners, obj


def test_a_sharp_chessboard_has_alike_edge_families() -> None:
    still = edge_blur(*chessboard(0.0, 0.0))
    assert still.across_x_px == pytest.approx(still.across_y_px, rel=0.05)
    assert 0.5 < still.sharp_px < 1.1  # the 0.8 px lens blur, less the sampling floor
    assert still.along_smear_px() < 1.0


@pytest.mark.parametrize(("smear", "direction", "rotation"), [(4.0, 0.0, 0.0), (4.0, 90.0, 0.0), (6.0, 0.0, 0.0),
                                                              (5.0, -25.0, 25.0)])
def test_edge_blur_measures_a_smear_along_its_direction(smear: float, direction: float, rotation: float) -> None:
    """A smear along the board's x axis widens the edges running along its y axis (across_y), not the others."""
    e = edge_blur(*chessboard(smear, direction, rotation_deg=rotation))
    along_x = (direction + rotation) % 180 == 0  # the smear runs along the board's x axis (rotation is counter-clockwise)
    widened, unwidened = (e.across_y_px, e.across_x_px) if along_x else (e.across_x_px, e.across_y_px)
    assert widened > 1.3 * unwidened, e
    assert unwidened < 1.1  # edges parallel to the motion stay as sharp as the still board's
    assert e.along_smear_px() == pytest.approx(smear, rel=0.3)
    assert e.along_widening() > 1.15  # the selector would call this frame moving


def test_edge_blur_without_enough_image_is_infinite() -> None:
    grey, corners, obj = chessboard(0.0, 0.0)
    inf = edge_blur(grey, corners[:3], obj[:3])
    assert np.isinf(inf.across_x_px) and np.isinf(inf.across_y_px)
    flat = edge_blur(np.full_like(grey, 128), corners, obj)  # no contrast
    assert np.isinf(flat.sharp_px) and np.isinf(flat.along_smear_px()) and np.isinf(flat.along_widening())
