"""The exposure read off a capture's edges and motion, and the frames it says smeared."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector, Detection
from calibcoach.coverage.exposure import (
    MAX_NEIGHBOUR_MOVE_PX,
    MIN_INFORMATIVE_FRAMES,
    ExposureReader,
    SmearLedger,
    corner_velocities,
    velocities_across,
    worst_corner_speed_px_s,
)
from calibcoach.coverage.sharpness import SAMPLING_FLOOR_PX, EdgeBlur, edge_blur, steepest_gradient_sigma
from calibcoach.drivers.sim import LENSES
from calibcoach.drivers.sim_paths import place_board
from calibcoach.drivers.sim_render import BoardRenderer, expose

SPEC = BoardSpec()
CAMERA = LENSES["webcam720"]
INTERVAL_S = 1 / 30


@pytest.fixture(scope="module")
def board_radiance():
    """The board at 0.7 m, still, before exposure (linear light), and its corners as detected."""
    renderer = BoardRenderer(CAMERA, SPEC, 2, False, False)
    rvec, tvec = place_board(CAMERA, SPEC, (640, 360), 0.7, tilt_x_deg=15, roll_deg=20)
    radiance = renderer.radiance_exposure([(rvec, tvec)])
    image = expose(radiance, rng=np.random.default_rng(0), blur_sigma_px=0.6, noise_sigma_dn=1.5)
    detection = CharucoBoardDetector(SPEC.with_detected(legacy=False, inverted=False)).detect(image)
    assert detection.corner_count >= 30
    return radiance, detection


def smeared(radiance: np.ndarray, length_px: float, angle_rad: float, seed: int) -> np.ndarray:
    """The frame of a board that moved `length_px` along `angle_rad` in the exposure: a translation
    parallel to the image smears the light by a line of that length (a box, sampled every 0.1 px)."""
    if length_px < 0.05:
        blurred = radiance
    else:
        size = int(np.ceil(length_px)) * 2 + 3
        kernel = np.zeros((size, size), np.float32)
        for s in np.linspace(-0.5, 0.5, max(3, int(length_px / 0.1))) * length_px:
            x, y = size // 2 + s * np.cos(angle_rad), size // 2 + s * np.sin(angle_rad)
            x0, y0 = int(np.floor(x)), int(np.floor(y))
            fx, fy = x - x0, y - y0  # bilinear splat: no sub-pixel step of the line is lost
            kernel[y0, x0] += (1 - fx) * (1 - fy)
            kernel[y0, x0 + 1] += fx * (1 - fy)
            kernel[y0 + 1, x0] += (1 - fx) * fy
            kernel[y0 + 1, x0 + 1] += fx * fy
        blurred = cv2.filter2D(radiance, -1, kernel / kernel.sum(), borderType=cv2.BORDER_REPLICATE)
    return expose(blurred, rng=np.random.default_rng(seed), blur_sigma_px=0.6, noise_sigma_dn=1.5)


@pytest.mark.parametrize("exposure_frames", [0.3, 0.6])
def test_the_exposure_is_read_off_moving_frames_edges(board_radiance, exposure_frames: float) -> None:
    radiance, detection = board_radiance
    exposure_s = exposure_frames * INTERVAL_S
    rng = np.random.default_rng(3)
    reader = ExposureReader()
    for k in range(40):
        speed_px_s = rng.uniform(0.0, 4.0) / exposure_s  # smears of 0-4 px, as a hand's tremor and slow moves make
        angle = rng.uniform(0, np.pi)
        image = smeared(radiance, speed_px_s * exposure_s, angle, seed=k)
        edges = edge_blur(image, detection.corners_px, detection.object_points_m)
        velocities = np.tile([speed_px_s * np.cos(angle), speed_px_s * np.sin(angle)], (detection.corner_count, 1))
        reader.add(edges, velocities)
    reading = reader.reading(INTERVAL_S)
    assert reading.informative_frames >= MIN_INFORMATIVE_FRAMES
    # read 5% long here; 17% before the reading allowed for the edge measure's own response to a
    # smear past the lens blur (`sharpness.steepest_gradient_sigma`)
    assert 0.95 * exposure_s < reading.exposure_s < 1.12 * exposure_s
    assert reading.relative_error < 0.1

def test_still_frames_leave_the_exposure_unknown(board_radiance) -> None:
    radiance, detection = board_radiance
    still = ExposureReader()  # still frames alone say nothing about the exposure: it is bounded by the frame interval
    for k in range(40):
        image = smeared(radiance, 0.0, 0.0, seed=100 + k)
        still.add(edge_blur(image, detection.corners_px, detection.object_points_m), np.zeros((detection.corner_count, 2)))
    unknown = still.reading(INTERVAL_S)
    assert unknown.exposure_s is None and "unknown" in unknown.describe()


def _detection(corners: np.ndarray) -> Detection:
    ids = np.arange(len(corners), dtype=np.int32)
    return Detection(corners.astype(np.float32), ids, np.zeros((len(corners), 3), np.float32), np.zeros(0, np.int32))


def test_corner_velocities_need_shared_corners_and_a_trackable_move() -> None:
    grid = np.stack(np.meshgrid(np.arange(4) * 40.0, np.arange(3) * 40.0), axis=-1).reshape(-1, 2) + 300
    before, after = _detection(grid), _detection(grid + [3.0, -4.0])
    v = corner_velocities(before, 0, after, int(2 * INTERVAL_S * 1e9))
    assert v is not None and np.allclose(v, [45.0, -60.0])  # 5 px over two frame intervals: 75 px/s
    assert worst_corner_speed_px_s(v) == pytest.approx(75.0)
    assert corner_velocities(before, 0, _detection(grid + [MAX_NEIGHBOUR_MOVE_PX + 1, 0]), int(1e8)) is None  # in transit
    assert corner_velocities(before, 0, _detection(grid[:3]), int(1e8)) is None  # 3 shared corners
    assert corner_velocities(before, 5, after, 5) is None  # no time between them


def test_velocities_across_a_frame_fall_back_to_the_faster_side_that_shows_the_board() -> None:
    grid = np.stack(np.meshgrid(np.arange(4) * 40.0, np.arange(3) * 40.0), axis=-1).reshape(-1, 2) + 300
    ns = round(INTERVAL_S * 1e9)
    here = (_detection(grid), ns)
    before, after = (_detection(grid - [1.0, 0]), 0), (_detection(grid + [3.0, 0]), 2 * ns)
    v = velocities_across(here, before, after)
    assert v is not None and np.allclose(v, [60.0, 0.0])  # 4 px over two intervals
    # a neighbour not seen (skipped in transit): the other side alone, one interval
    v = velocities_across(here, None, after)
    assert v is not None and np.allclose(v, [90.0, 0.0])
    v = velocities_across(here, before, None)
    assert v is not None and np.allclose(v, [30.0, 0.0])
    # the frame after shows too little of the board to go across: the faster of the sides that tell
    v = velocities_across(here, before, (_detection(grid[:3] + [3.0, 0]), 2 * ns))
    assert v is not None and np.allclose(v, [30.0, 0.0])
    v = velocities_across(here, (_detection(grid + [-6.0, 0]), 0), (_detection(grid + [2.0, 0]), 2 * ns))
    assert v is not None and np.allclose(v, [120.0, 0.0])  # across 8 px / 2 intervals
    # across, the board moved past a neighbour's limit (27 px): each side alone, the faster
    v = velocities_across(here, (_detection(grid - [15.0, 0]), 0), (_detection(grid + [12.0, 0]), 2 * ns))
    assert v is not None and np.allclose(v, [450.0, 0.0])
    assert velocities_across(here, None, None) is None


def _ledger_with(speeds_px_frame: dict[int, float], *, exposure_frames: float | None) -> SmearLedger:
    ledger = SmearLedger()
    for index in range(100):
        ledger.saw(index, round(index * INTERVAL_S * 1e9))
    for index, speed in speeds_px_frame.items():
        ledger.record(index, speed / INTERVAL_S)
    if exposure_frames is not None:  # frames whose edges show that exposure: x family widened by the motion
        blur = np.hypot(0.6, SAMPLING_FLOOR_PX)  # across it, as the edge measure reads a 0.6 px edge smeared so
        for k in range(60):
            move = 0.5 + 2.5 * (k % 10) / 10  # px a frame, across the x family only
            measured = float(steepest_gradient_sigma(blur, move * exposure_frames))
            ledger.reader.add(EdgeBlur(float(np.sqrt(measured**2 - SAMPLING_FLOOR_PX**2)), 0.6, ((0.0, 1.0), (1.0, 0.0))),
                              np.array([[0.0, move / INTERVAL_S]] * 8))
    return ledger


def test_smeared_frames_are_those_moving_past_the_limit_within_the_exposure() -> None:
    speeds = {1: 0.5, 2: 1.4, 3: 2.0, 4: 4.0, 5: 8.0}  # px a frame at each frame's fastest corner
    # an exposure the frames could not show: none is judged by it (the frame interval bounds it only loosely)
    smeared, reading = _ledger_with(speeds, exposure_frames=None).smeared(list(speeds), 1.5)
    assert smeared == set() and reading is not None and reading.exposure_s is None
    # a quarter-interval exposure read off the edges: only moves over 6 px a frame smear 1.5 px
    smeared, reading = _ledger_with(speeds, exposure_frames=0.25).smeared(list(speeds), 1.5)
    assert reading.exposure_s == pytest.approx(0.25 * INTERVAL_S, rel=0.02)
    assert smeared == {5}
    # the whole interval: everything over 1.5 px a frame
    smeared, reading = _ledger_with(speeds, exposure_frames=1.0).smeared(list(speeds), 1.5)
    assert reading.exposure_s == pytest.approx(INTERVAL_S, rel=0.02) and smeared == {3, 4, 5}
    # frames whose speed is unknown are never counted smeared
    assert _ledger_with({}, exposure_frames=1.0).smeared([1, 2], 1.5)[0] == set()
