"""Smear within the exposure, measured from the frame: renders with a known smear length."""

from __future__ import annotations

import numpy as np
import pytest

from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector
from calibcoach.coverage.sharpness import edge_blur, steepest_gradient_sigma, upper_percentile
from calibcoach.drivers.sim import LENSES
from calibcoach.drivers.sim_paths import place_board
from calibcoach.drivers.sim_render import BoardRenderer, expose

SPEC = BoardSpec()
CAMERA = LENSES["webcam720"]


def smeared_frame(length_px: float, direction: tuple[float, float], *, roll_deg: float = 0.0, seed: int = 1):
    """The board at 0.7 m moved by `length_px` along `direction` during the exposure (centred)."""
    renderer = BoardRenderer(CAMERA, SPEC, 2, False, False)
    rvec, tvec = place_board(CAMERA, SPEC, (640, 360), 0.7, tilt_x_deg=15, roll_deg=roll_deg)
    metres = length_px * tvec[2] / CAMERA.fx
    steps = np.linspace(-0.5, 0.5, max(2, int(np.ceil(length_px / 0.25)) + 1)) * metres if length_px > 0 else [0.0]
    poses = [(rvec, tvec + np.array([s * direction[0], s * direction[1], 0.0])) for s in steps]
    image = expose(renderer.radiance_exposure(poses), rng=np.random.default_rng(seed), blur_sigma_px=0.6, noise_sigma_dn=1.5,
                   vignetting=0.2, off_axis_rad=renderer.off_axis_rad)
    detection = CharucoBoardDetector(SPEC.with_detected(legacy=False, inverted=False)).detect(image)
    assert detection.corner_count >= 30
    return edge_blur(image, detection.corners_px, detection.object_points_m)


def test_a_still_frame_shows_no_smear_and_both_edge_families_alike() -> None:
    still = smeared_frame(0.0, (1.0, 0.0))
    assert still.across_x_px == pytest.approx(still.across_y_px, abs=0.1)
    assert 0.5 < still.sharp_px < 1.2  # 0.6 px lens blur plus the renderer's own spread
    assert still.along_smear_px() < 0.8 and still.diagonal_smear_px(still.sharp_px) < 0.1


@pytest.mark.parametrize(("length", "direction", "roll"), [(2.0, (1.0, 0.0), 0.0), (3.0, (0.0, 1.0), 0.0),
                                                           (3.0, (1.0, 0.0), 30.0), (2.0, (0.7071, 0.7071), 0.0)])
def test_smear_length_is_read_off_the_image(length: float, direction, roll: float) -> None:
    own = smeared_frame(0.0, (1.0, 0.0), roll_deg=roll).sharp_px  # this camera's sharpness, from a still frame
    edges = smeared_frame(length, direction, roll_deg=roll)
    diagonal = abs(direction[0]) == pytest.approx(abs(direction[1]))
    measured = edges.diagonal_smear_px(own) if diagonal else edges.along_smear_px()
    widening = edges.diagonal_widening(own) if diagonal else edges.along_widening()
    assert measured == pytest.approx(length, rel=0.45), measured  # the box blur's width, within the measure's scatter
    assert measured > 1.5 and widening > 1.15  # the selector's limits: each of these is rejected as moving


def test_a_soft_but_unsmeared_image_is_not_called_smeared() -> None:
    # a real close-range photo set (pycamset cam 2) shows edges 2.6 and 2.7 px wide: "3 px of smear"
    # by the difference of squares, but 4% of widening, which the selector does not count
    from calibcoach.coverage.sharpness import EdgeBlur

    soft = EdgeBlur(2.60, 2.71)
    assert soft.along_smear_px() > 2.0 and soft.along_widening() < 1.05


@pytest.mark.parametrize("pct", [50.0, 95.0, 99.5, 100.0])
def test_upper_percentile_is_numpys_number_bit_for_bit(pct: float) -> None:
    rng = np.random.default_rng(int(pct * 10))
    cases = [
        rng.gamma(2.0, 3.0, 100_000).astype(np.float32),  # gradient magnitudes: a long upper tail
        rng.gamma(2.0, 3.0, 777).astype(np.float64),
        np.concatenate([np.ones(5000, np.float32), [1e6]]).astype(np.float32),  # one outlier: the quarter-max guess holds too few
        np.concatenate([np.ones(5000, np.float32), [3.0]]).astype(np.float32),  # 0.6 of the max holds too few, a quarter enough
        np.full(300, 7.5, np.float32),  # all alike
        rng.integers(0, 4, 1001).astype(np.float32),  # ties at the wanted ranks
        np.array([3.0], np.float32),
    ]
    for values in cases:
        expected = np.percentile(values, pct)
        got = upper_percentile(values, pct)
        assert got == expected and np.asarray(got).dtype == np.asarray(expected).dtype, (values.size, pct, got, expected)


def test_the_steepest_gradient_width_of_a_smeared_edge() -> None:
    sigma = 0.8
    small = np.array([0.1, 0.5, 1.0])  # under the blur: the variance model, sigma^2 + L^2 / 12
    np.testing.assert_allclose(steepest_gradient_sigma(sigma, small), np.sqrt(sigma**2 + small**2 / 12), rtol=3e-3)
    assert float(steepest_gradient_sigma(sigma, 0.0)) == pytest.approx(sigma)
    large = np.array([20.0, 40.0])  # far past it: the gradient is the contrast over the smear's length
    np.testing.assert_allclose(steepest_gradient_sigma(sigma, large), large / np.sqrt(2 * np.pi), rtol=1e-6)
    # in between the squared width grows faster than the variance model's L^2 / 12, up to 12 / (2 pi) times
    L = np.linspace(0.5, 30, 60)
    excess = (steepest_gradient_sigma(sigma, L) ** 2 - sigma**2) / (L**2 / 12)
    assert np.all(np.diff(excess) > 0) and 1.0 < excess[0] and excess[-1] < 12 / (2 * np.pi)
