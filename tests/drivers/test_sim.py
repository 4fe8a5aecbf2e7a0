"""The simulator is the ground truth of every accuracy test, so it is tested against geometry first.

- Rendering: the image matches an independent homography warp of the same texture (pixel-centre
  conventions, with and without supersampling), and the ChArUco detector finds the corners where
  the lens model projects them (no bias; sub-0.05 px median through a focused lens).
- Print variants: an inverted print is found as inverted, a legacy print of an even-row board only
  with the legacy pattern.
- Lenses: each preset's field of view, and a one-to-one mapping over the whole image.
- Paths: frontal stays frontal, careful covers the four quadrants and tilts beyond 45 deg, the board
  stays in front of the camera, sloppy loses the board now and then.
- The camera: deterministic given a seed; low light is darker and noisier; its info and truth.

Images are small (640x360 variants) except in the corner-accuracy test, which uses the presets as
they are: at 640x360 an 8x11 board has ~25 px squares, where OpenCV's sub-pixel refinement alone
scatters by ~0.08 px, which would hide what is being measured.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector
from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.sim import (
    LENSES,
    SimulatedCamera,
    board_tilt_deg,
    handheld_path,
    handheld_trajectory,
    place_board,
    render_board_view,
)
from calibcoach.drivers.sim_paths import (
    MIN_DEPTH_M,
    board_centre_m,
    board_outline_m,
    distance_for_height,
    image_points,
)
from calibcoach.drivers.sim_render import (
    INK_REFLECTANCE,
    PAPER_REFLECTANCE,
    TEXTURE_PX_PER_SQUARE,
    BoardRenderer,
    pose_matrix,
)

SPEC = BoardSpec(legacy=False, inverted=False)  # settled: the accuracy tests do not probe variants
SMALL = (640, 360)


def _corner_errors(camera: CameraModel, image: np.ndarray, rvec, tvec, spec: BoardSpec = SPEC) -> np.ndarray:
    """(N, 2) detected minus projected corner positions, pixels."""
    det = CharucoBoardDetector(spec).detect(image)
    assert det.corner_count >= 40, f"only {det.corner_count} corners detected"
    return det.corners_px.astype(np.float64) - camera.project(det.object_points_m, rvec, tvec)


# --- rendering geometry ---------------------------------------------------------------------------


def _warp_reference(camera: CameraModel, rvec, tvec, *, shift_px: float = 0.0) -> np.ndarray:
    """The board texture warped by the plane's homography: an independent render of an undistorted view.

    Texture texel (u, v) has its centre at board point ((u + 0.5) / texels_per_m - margin, ...),
    with the chessboard starting one square (128 texels) in from the texture's edge.
    """
    pps = TEXTURE_PX_PER_SQUARE
    size = ((SPEC.squares_x + 2) * pps, (SPEC.squares_y + 2) * pps)
    printed = SPEC.cv_board().generateImage(size, marginSize=pps, borderBits=1).astype(np.float32) / 255.0
    texture = INK_REFLECTANCE + (PAPER_REFLECTANCE - INK_REFLECTANCE) * printed
    square_m = SPEC.square_mm / 1000.0
    per_m = pps / square_m
    texel_to_board = np.array([[1 / per_m, 0, 0.5 / per_m - square_m], [0, 1 / per_m, 0.5 / per_m - square_m], [0, 0, 1]])
    R = pose_matrix(rvec)
    K = camera.camera_matrix.copy()
    K[0, 2] += shift_px
    H = K @ np.column_stack([R[:, 0], R[:, 1], np.asarray(tvec, np.float64)]) @ texel_to_board
    return cv2.warpPerspective(texture, H, camera.image_size, flags=cv2.INTER_LINEAR)


@pytest.mark.parametrize("supersample", [1, 2])
def test_render_matches_homography_warp(supersample: int) -> None:
    """Ray casting equals an independent homography warp, so pixel (0, 0) is a pixel's centre.

    A long lens (f = 2000 px) close to the board keeps every texel larger than a pixel, so the
    renderer samples mip level 0 only, like the warp. With supersampling the reference is warped
    at twice the size (principal point (c + 0.5) * 2 - 0.5, worked out here, not by
    CameraModel.resized) and area-averaged; a 0.25 px error there would show as a shift.
    """
    w, h = SMALL
    K = np.array([[2000.0, 0, (w - 1) / 2 + 3.3], [0, 2000.0, (h - 1) / 2 - 2.1], [0, 0, 1]])
    camera = CameraModel("pinhole", K, np.zeros(5), SMALL)
    rvec, tvec = place_board(camera, SPEC, (w / 2, h / 2), 0.4, tilt_x_deg=15, tilt_y_deg=-10, roll_deg=8)
    renderer = BoardRenderer(camera, SPEC, supersample=supersample)
    rendered = renderer.radiance(rvec, tvec) / renderer.brightness(rvec)  # (H, W) paper reflectance
    if supersample == 1:
        reference = _warp_reference(camera, rvec, tvec)
        shifted = _warp_reference(camera, rvec, tvec, shift_px=0.25)
    else:
        K2 = K.copy()
        K2[:2, :2] *= 2
        K2[:2, 2] = (K[:2, 2] + 0.5) * 2 - 0.5
        big = CameraModel("pinhole", K2, np.zeros(5), (2 * w, 2 * h))
        reference = cv2.resize(_warp_reference(big, rvec, tvec), SMALL, interpolation=cv2.INTER_AREA)
        shifted = cv2.resize(_warp_reference(big, rvec, tvec, shift_px=0.5), SMALL, interpolation=cv2.INTER_AREA)
    inner = (slice(4, h - 4), slice(4, w - 4))  # the whole view is paper; skip the warp's border pixels
    diff = np.abs(rendered - reference)[inner]
    # Both sample bilinearly with 1/32-texel fixed-point coordinates: on a 0.8-contrast edge the two
    # may differ by ~0.8 / 32 = 0.025; a quarter-pixel shift moves edge pixels by ~0.2.
    assert diff.max() < 0.04, f"renderer and homography warp differ by up to {diff.max():.3f}"
    assert diff.mean() < 0.002
    assert np.abs(shifted - reference)[inner].max() > 0.15, "the comparison must be able to see a 0.25 px shift"


def test_texture_squares_sit_on_texel_edges() -> None:
    """generateImage with a 128-texel margin puts square j exactly on texels [128 (j + 1), 128 (j + 2))."""
    pps = TEXTURE_PX_PER_SQUARE
    img = SPEC.cv_board().generateImage(((SPEC.squares_x + 2) * pps, (SPEC.squares_y + 2) * pps),
                                        marginSize=pps, borderBits=1)
    row = img[pps + pps // 2].astype(int)  # through the middle of the first square row
    edges = np.flatnonzero(np.diff(row)) + 1
    assert edges[0] == pps and edges[1] == 2 * pps  # the black top-left square spans texels 128..255


@pytest.mark.parametrize("lens", ["webcam720", "fisheye150"])
def test_detected_corners_match_projection(lens: str) -> None:
    """Detected ChArUco corners land where CameraModel.project puts them, frontal and tilted.

    Sharp images (no blur, no noise) measure the renderer: the mean error vector (the bias a
    pixel-centre bug shows as a 0.25-0.5 px offset) stays below 0.02 px. The scatter of single
    corners is OpenCV's cornerSubPix on box-filtered edges: 0.04-0.10 px median depending on how
    the edges cross the pixel grid, the same on an analytically area-sampled chessboard, so the
    0.05 px median bound is checked through the simulated camera's focused lens (0.6 px blur).
    """
    camera = LENSES[lens]
    w, h = camera.image_size
    distance = distance_for_height(camera, SPEC, 0.6)
    views = {"frontal": (0.0, 0.0), "tilted": (25.0, -25.0)}  # tilt_x, tilt_y: 35 deg in all
    for name, (tilt_x, tilt_y) in views.items():
        rvec, tvec = place_board(camera, SPEC, (w / 2, h / 2), distance, tilt_x_deg=tilt_x, tilt_y_deg=tilt_y)
        sharp = _corner_errors(camera, render_board_view(camera, SPEC, rvec, tvec), rvec, tvec)
        bias = np.linalg.norm(sharp.mean(axis=0))
        assert bias < 0.02, f"{lens} {name}: corners are offset by {sharp.mean(axis=0)} px on average"
        dist = np.linalg.norm(sharp, axis=1)
        assert np.median(dist) < 0.08 and np.percentile(dist, 95) < 0.15, f"{lens} {name} sharp: {np.median(dist):.3f}"
        focused = render_board_view(camera, SPEC, rvec, tvec, blur_sigma_px=0.6)
        dist = np.linalg.norm(_corner_errors(camera, focused, rvec, tvec), axis=1)
        assert np.median(dist) < 0.05, f"{lens} {name}: median corner error {np.median(dist):.3f} px"
        assert np.percentile(dist, 95) < 0.15, f"{lens} {name}: p95 corner error {np.percentile(dist, 95):.3f} px"


def test_board_behind_or_turned_away_shows_background() -> None:
    camera = LENSES["webcam720"].resized(SMALL)
    renderer = BoardRenderer(camera, SPEC)
    empty = renderer.radiance(np.zeros(3), np.array([0.0, 0.0, -1.0]))  # the board behind the camera
    turned = renderer.radiance(np.array([0.0, np.pi, 0.0]), np.array([0.12, -0.165, 0.6]))  # back side facing us
    np.testing.assert_array_equal(empty, turned)


# --- print variants -------------------------------------------------------------------------------


def test_inverted_print_is_detected_as_inverted() -> None:
    camera = LENSES["webcam720"].resized(SMALL)
    spec = BoardSpec()  # legacy and inverted left for the detector to find
    rvec, tvec = place_board(camera, spec, (320, 180), distance_for_height(camera, spec, 0.85), tilt_x_deg=10)
    image = render_board_view(camera, spec, rvec, tvec, inverted=True, blur_sigma_px=0.6, noise_sigma_dn=1.0)
    detector = CharucoBoardDetector(spec)
    assert detector.detect(image).corner_count >= 20
    assert detector.variant_found == "inverted print"


def test_legacy_pattern_of_even_row_board_detects_only_as_legacy() -> None:
    """OpenCV 4.6 changed the pattern for even row counts: an old 8x10 print needs --legacy."""
    camera = LENSES["webcam720"].resized(SMALL)
    spec = BoardSpec(squares_x=8, squares_y=10)
    rvec, tvec = place_board(camera, spec, (320, 180), distance_for_height(camera, spec, 0.85))
    image = render_board_view(camera, spec, rvec, tvec, legacy=True, blur_sigma_px=0.6, noise_sigma_dn=1.0)
    assert CharucoBoardDetector(BoardSpec(8, 10, legacy=False, inverted=False)).detect(image).corner_count == 0
    assert CharucoBoardDetector(BoardSpec(8, 10, legacy=True, inverted=False)).detect(image).corner_count >= 30
    # Polarity settled, so the automatic choice is between the two patterns only. (Left open,
    # the detector's inverted mode finds a marker or two more on this plain print and wins.)
    auto = CharucoBoardDetector(BoardSpec(8, 10, inverted=False))
    auto.detect(image)
    assert auto.variant_found == "legacy pattern"


# --- lenses ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(("lens", "hfov_deg"), [("webcam720", 70), ("wide720", 115), ("fisheye150", 150), ("webcam1080", 75)])
def test_lens_preset_field_of_view_and_one_to_one_mapping(lens: str, hfov_deg: float) -> None:
    camera = LENSES[lens]
    assert camera.field_of_view_deg()[0] == pytest.approx(hfov_deg, abs=0.5)
    w, h = camera.image_size
    ys, xs = np.mgrid[-0.5:h:8.0, -0.5:w:8.0]
    pixels = np.concatenate([np.stack([xs.ravel(), ys.ravel()], 1), [[w - 0.5, h - 0.5], [-0.5, h - 0.5], [w - 0.5, -0.5]]])
    assert np.abs(camera.project(camera.unproject(pixels)) - pixels).max() < 1e-6
    # Monotonic: the angle off axis keeps growing along the diagonals out to every image corner.
    cx, cy = camera.principal_point
    s = np.linspace(0.0, 1.0, 400)[:, None]
    for corner in ([-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]):
        rays = camera.unproject(np.array([cx, cy]) + s * (np.array(corner) - [cx, cy]))
        assert np.all(np.diff(np.arccos(np.clip(rays[:, 2], -1, 1))) > 0)


# --- paths ----------------------------------------------------------------------------------------


def test_place_board_follows_the_tilt_conventions() -> None:
    camera = LENSES["webcam720"]
    rvec, tvec = place_board(camera, SPEC, (900, 200), 0.8, tilt_x_deg=20)
    tilt, tilt_x, tilt_y = board_tilt_deg(rvec, tvec, SPEC)
    assert (tilt, tilt_x, tilt_y) == pytest.approx((20, 20, 0), abs=1e-6)
    corners = board_outline_m(SPEC, per_edge=1) @ pose_matrix(rvec).T + tvec  # TL, TR, BR, BL
    assert corners[0, 2] > corners[3, 2]  # positive tilt_x: the top edge is further away
    rvec, tvec = place_board(camera, SPEC, (640, 360), 0.8, tilt_y_deg=35)
    corners = board_outline_m(SPEC, per_edge=1) @ pose_matrix(rvec).T + tvec
    assert corners[1, 2] > corners[0, 2]  # positive tilt_y: the right edge is further away
    centre = pose_matrix(rvec) @ board_centre_m(SPEC) + tvec
    np.testing.assert_allclose(camera.project(centre[None]), [[640, 360]], atol=1e-6)


def test_frontal_path_stays_frontal() -> None:
    camera = LENSES["webcam720"]
    poses = handheld_path(camera, SPEC, "frontal", seconds=20, fps=10, seed=3)
    assert len(poses) == 200
    for pose in poses:
        normal = pose_matrix(pose.rvec)[:, 2]
        assert board_tilt_deg(pose.rvec, pose.tvec, SPEC)[0] < 8.0
        assert np.degrees(np.arccos(normal[2])) < 8.0  # also against the optical axis


def _centres_px(camera: CameraModel, poses) -> np.ndarray:
    return np.array([camera.project((pose_matrix(p.rvec) @ board_centre_m(SPEC) + p.tvec)[None])[0] for p in poses])


@pytest.mark.parametrize("lens", ["webcam720", "fisheye150"])
def test_careful_path_covers_quadrants_and_big_tilts(lens: str) -> None:
    camera = LENSES[lens]
    poses = handheld_path(camera, SPEC, "careful", seconds=20, fps=10, seed=1)
    w, h = camera.image_size
    centres = _centres_px(camera, poses)
    left, top = centres[:, 0] < w / 2, centres[:, 1] < h / 2
    for name, in_quadrant in {"TL": left & top, "TR": ~left & top, "BR": ~left & ~top, "BL": left & ~top}.items():
        assert in_quadrant.sum() >= 10, f"the careful path spends only {in_quadrant.sum()} frames in the {name} quadrant"
    tilts = np.array([board_tilt_deg(p.rvec, p.tvec, SPEC) for p in poses])
    assert tilts[:, 0].max() >= 45
    assert tilts[:, 1].min() <= -30 and tilts[:, 1].max() >= 30  # both signs about both axes
    assert tilts[:, 2].min() <= -30 and tilts[:, 2].max() >= 30
    # The careful user keeps the whole chessboard in view while holding still.
    outline = board_outline_m(SPEC)
    seen = [np.all(image_points(camera, outline @ pose_matrix(p.rvec).T + p.tvec)[1]) for p in poses]
    assert np.mean(seen) > 0.9


@pytest.mark.parametrize("style", ["careful", "sloppy", "frontal"])
def test_paths_keep_the_board_in_front_of_the_fisheye(style: str) -> None:
    camera = LENSES["fisheye150"]
    corners = board_outline_m(SPEC, per_edge=1)
    for pose in handheld_path(camera, SPEC, style, seconds=15, fps=10, seed=5):
        assert (corners @ pose_matrix(pose.rvec).T + pose.tvec)[:, 2].min() >= MIN_DEPTH_M - 1e-9


def test_sloppy_path_loses_the_board_now_and_then() -> None:
    camera = LENSES["webcam720"]
    w, h = camera.image_size
    outline = board_outline_m(SPEC)
    visible = []
    for pose in handheld_path(camera, SPEC, "sloppy", seconds=20, fps=10, seed=2):
        px, seen = image_points(camera, outline @ pose_matrix(pose.rvec).T + pose.tvec)
        inside = seen & (px[:, 0] >= 0) & (px[:, 0] <= w - 1) & (px[:, 1] >= 0) & (px[:, 1] <= h - 1)
        visible.append(inside.mean())
    visible = np.array(visible)
    assert np.any(visible == 0), "no frame without the board"
    assert np.any((visible > 0) & (visible < 1)), "the board never leaves the image partly"


def test_path_is_deterministic_given_a_seed() -> None:
    camera = LENSES["wide720"]
    a = handheld_path(camera, SPEC, "sloppy", seconds=5, fps=10, seed=7)
    b = handheld_path(camera, SPEC, "sloppy", seconds=5, fps=10, seed=7)
    c = handheld_path(camera, SPEC, "sloppy", seconds=5, fps=10, seed=8)
    assert all(np.array_equal(p.tvec, q.tvec) and np.array_equal(p.rvec, q.rvec) for p, q in zip(a, b, strict=True))
    assert not all(np.array_equal(p.tvec, q.tvec) for p, q in zip(a, c, strict=True))


# --- the simulated camera -------------------------------------------------------------------------


def _small_camera(**kwargs) -> SimulatedCamera:
    camera = LENSES["webcam720"].resized(SMALL)
    trajectory = handheld_trajectory(camera, SPEC, "careful", seconds=3, seed=1)
    return SimulatedCamera(camera, SPEC, trajectory.sample(seconds=3, fps=10), trajectory=trajectory, **kwargs)


def test_simulated_camera_is_deterministic_given_a_seed() -> None:
    first = [f.image for f in _small_camera(seed=4)]
    again = _small_camera(seed=4)
    assert len(first) == 30 and first[0].shape == (360, 640) and first[0].dtype == np.uint8
    for i in (0, 11, 29):  # alone or in sequence, frame i is the same image
        np.testing.assert_array_equal(again.render(i), first[i])
    assert not np.array_equal(_small_camera(seed=5).render(0), first[0])


def test_low_light_is_darker_and_noisier() -> None:
    normal, dim = _small_camera(), _small_camera(low_light=True)
    normal_other, dim_other = _small_camera(seed=9), _small_camera(low_light=True, seed=9)
    a, b = normal.render(0).astype(float), normal_other.render(0).astype(float)
    c, d = dim.render(0).astype(float), dim_other.render(0).astype(float)
    assert c.mean() < 0.6 * a.mean()
    noise_normal, noise_dim = np.std(a - b) / np.sqrt(2), np.std(c - d) / np.sqrt(2)  # two seeds, same scene
    assert noise_normal == pytest.approx(1.5, rel=0.15)
    assert noise_dim > 1.8 * noise_normal


def test_motion_blur_follows_the_moving_board() -> None:
    source = _small_camera(noise_sigma=0.0)
    moving = np.array([len(source.exposure_poses(i)) for i in range(len(source.poses))])
    assert moving[0] == 1  # the first target is held still
    assert moving.max() > 1  # and the moves in between are smeared


def test_simulated_camera_info_and_truth() -> None:
    camera = LENSES["webcam720"]
    poses = handheld_path(camera, SPEC, "frontal", seconds=1, fps=10, seed=0)
    source = SimulatedCamera(camera, SPEC, poses, inverted=True)
    info = source.info
    assert info.kind == "sim" and info.camera_id == "sim:webcam720"
    assert info.image_size == (1280, 720) and info.fps == pytest.approx(10.0) and info.frame_count == 10
    assert dict(info.controls) == {"focus_absolute": 0.0}
    assert info.board is not None and info.board["inverted"] is True
    assert source.truth.camera is camera and source.truth.poses == tuple(poses)
    assert SimulatedCamera(camera.resized(SMALL), SPEC, poses).info.camera_id == "sim:custom"
    with pytest.raises(ValueError, match="at least one pose"):
        SimulatedCamera(camera, SPEC, [])


def test_low_light_doubles_the_exposure_up_to_the_frame_interval() -> None:
    camera = LENSES["webcam720"]
    poses = handheld_path(camera, SPEC, "frontal", seconds=1, fps=30, seed=0)
    assert SimulatedCamera(camera, SPEC, poses, exposure_s=0.01, low_light=True).exposure_s == pytest.approx(0.02)
    # 2 x 30 ms would outlast a 30 fps frame: a camera cannot expose longer than it takes to deliver a frame
    assert SimulatedCamera(camera, SPEC, poses, exposure_s=0.03, low_light=True).exposure_s == pytest.approx(1 / 30, rel=1e-6)
    assert SimulatedCamera(camera, SPEC, poses, exposure_s=0.03).exposure_s == pytest.approx(0.03)


def test_poses_at_several_distances_are_each_the_single_pose_and_face_the_ray() -> None:
    # The candidate grid builds one orientation for its three ranges: each pose must be the very
    # number `pose_facing_pixel` gives alone (same candidates, same guidance), at its distance on the ray.
    from calibcoach.drivers.geometry import pose_facing_pixel, poses_facing_pixel

    ray, centre = np.array([0.3, -0.2, 1.0]), np.array([0.12, 0.165, 0.0])
    rvec, tvecs = poses_facing_pixel(ray, centre, [0.4, 0.7, 1.3], tilt_x_deg=35.0, tilt_y_deg=-20.0)
    for distance, tvec in zip([0.4, 0.7, 1.3], tvecs, strict=True):
        alone = pose_facing_pixel(ray, centre, distance, tilt_x_deg=35.0, tilt_y_deg=-20.0)
        assert np.array_equal(alone[0], rvec) and np.array_equal(alone[1], tvec)
        centre_cam = cv2.Rodrigues(rvec)[0] @ centre + tvec
        np.testing.assert_allclose(centre_cam, distance * ray / np.linalg.norm(ray), atol=1e-12)


def test_a_fine_smear_step_shows_the_small_smears_a_held_board_makes() -> None:
    """At the default 2 px between sub-frames, each half of an exposure that moves under 2 px is
    drawn as one sharp image; at 0.5 px those frames are drawn smeared, fewer of them the shorter
    the exposure. (12 s of a careful hand at 30 fps: 157 of 360 frames smeared at 2 px, 209 at 0.5.)"""
    camera = LENSES["webcam720"]
    trajectory = handheld_trajectory(camera, SPEC, "careful", seconds=12, seed=1)
    poses = trajectory.sample(seconds=12, fps=30.0)

    def smeared(step_px: float, exposure_s: float) -> np.ndarray:
        source = SimulatedCamera(camera, SPEC, poses, trajectory=trajectory, exposure_s=exposure_s, smear_step_px=step_px)
        return np.array([len(source.exposure_poses(i)) > 1 for i in range(len(poses))])

    coarse, fine = smeared(2.0, 0.024), smeared(0.5, 0.024)
    assert not np.any(coarse & ~fine)  # every smear the coarse step draws, the fine one draws too
    assert np.count_nonzero(fine & ~coarse) >= 30  # and ~50 small ones it drew sharp
    assert np.count_nonzero(smeared(0.5, 0.010)) < np.count_nonzero(fine)
    with pytest.raises(ValueError, match="smear_step_px"):
        SimulatedCamera(camera, SPEC, poses, smear_step_px=0.0)
