"""The covariance read off the scatter between holds (app/solve/hold_jackknife.py), on synthetic holds.

Each capture is 16 holds of 25 frames: one pose per hold (a hair of tremor), every frame with its
own gaussian corner noise. In the "shared" captures each hold also carries a smooth error field of
its own over the board (a quadratic in the image, ~0.05 px): what a hold's blur, compression or
tracking chain adds to all its frames alike. Residual correlation does not see it (it is small
against each corner's noise), so the model covariance counts the 400 frames as independent and
its E falls short of the true error; the jackknife over holds sees it.
"""

from __future__ import annotations

import numpy as np
import pytest

from calibcoach.app.solve import uncertainty as U
from calibcoach.app.solve.compare import projection_difference
from calibcoach.app.solve.hold_jackknife import MIN_HOLDS, hold_jackknife_covariance
from calibcoach.app.solve.result import View
from calibcoach.app.solve.robust import robust_calibrate, with_look_alikes_weighted
from calibcoach.drivers.sim import LENSES

from _synthetic import BOARD, IDS, SIZE, random_poses

CAMERA = LENSES["webcam720"]
GRID = (32, 18)


def capture(seed: int, *, shared_px: float, holds: int = 16, frames: int = 25, noise_px: float = 0.15):
    """(views, hold of each view): `holds` poses, `frames` frames each."""
    rng = np.random.default_rng(seed)
    poses = random_poses(CAMERA, holds, rng, region=(0.1, 0.9), distance_m=(0.4, 0.7), tilt_deg=40)
    views, hold_of = [], []
    for hold, (r, t) in enumerate(poses):
        x = (CAMERA.project(BOARD, r, t) - np.array(SIZE) / 2.0) / 640.0
        terms = np.stack([np.ones(len(x)), x[:, 0], x[:, 1], x[:, 0] ** 2, x[:, 0] * x[:, 1], x[:, 1] ** 2], axis=1)
        field = terms @ rng.normal(0.0, shared_px, (6, 2))  # this hold's own smooth error over the board
        for _ in range(frames):
            px = CAMERA.project(BOARD, r + rng.normal(0, 2e-4, 3), t + rng.normal(0, 2e-4, 3))
            views.append(View(len(views), "", IDS, px + field + rng.normal(0.0, noise_px, px.shape), BOARD))
            hold_of.append(hold)
    return views, hold_of


def errors(seed: int, shared_px: float) -> tuple[float, float, float]:
    """(true error, model E, jackknife E) over the covered region, px."""
    views, holds = capture(seed, shared_px=shared_px)
    cal = robust_calibrate(views, SIZE, "pinhole")
    mask = U.covered_region_mask(SIZE, [v.image_points_px for v in views], GRID)
    weighted, _rho = with_look_alikes_weighted(cal, holds)
    model = U.projection_uncertainty(weighted.camera, weighted.intrinsic_covariance, covered_mask_fn=lambda gx, gy: mask)
    between = hold_jackknife_covariance(cal.camera, cal.views, cal.rvecs, cal.tvecs, cal.residuals_px, holds)
    assert between is not None
    truth = projection_difference(CAMERA, cal.camera, grid=GRID, mask=mask).rms_px
    return truth, model.expected_error_px, U.expected_error_px(between, model.error_weight)


@pytest.fixture(scope="module")
def shared() -> np.ndarray:
    return np.array([errors(seed, 0.05) for seed in range(4)])


def test_error_shared_within_holds_is_seen_by_the_jackknife_not_the_model(shared: np.ndarray) -> None:
    truth, model, between = (np.sqrt(np.mean(shared[:, k] ** 2)) for k in range(3))
    assert truth > 1.2 * model  # the model, blind to what a hold shares, understates
    assert between >= truth  # the jackknife covers it
    assert np.mean(shared[:, 2] / shared[:, 1]) > 1.4


def test_independent_noise_gives_the_model_and_the_jackknife_alike() -> None:
    ratios = [between / model for _truth, model, between in (errors(seed, 0.0) for seed in range(3))]
    assert 0.6 < min(ratios) and max(ratios) < 1.4 and 0.8 < np.mean(ratios) < 1.2


def test_too_few_holds_or_single_frame_holds_read_no_covariance() -> None:
    views, holds = capture(0, shared_px=0.0, holds=MIN_HOLDS - 1, frames=3)
    cal = robust_calibrate(views, SIZE, "pinhole")
    assert hold_jackknife_covariance(cal.camera, cal.views, cal.rvecs, cal.tvecs, cal.residuals_px, holds) is None
    views, holds = capture(0, shared_px=0.0, holds=2 * MIN_HOLDS, frames=1)  # photos: nothing shared within a hold
    cal = robust_calibrate(views, SIZE, "pinhole")
    assert hold_jackknife_covariance(cal.camera, cal.views, cal.rvecs, cal.tvecs, cal.residuals_px, holds) is None
    views, holds = capture(0, shared_px=0.0, holds=MIN_HOLDS, frames=3)
    cal = robust_calibrate(views, SIZE, "pinhole")
    covariance = hold_jackknife_covariance(cal.camera, cal.views, cal.rvecs, cal.tvecs, cal.residuals_px, holds)
    assert covariance is not None and covariance.shape == (9, 9) and np.all(np.linalg.eigvalsh(covariance) > -1e-12)
