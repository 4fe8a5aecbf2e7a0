"""The weighted refinement's Levenberg-Marquardt damping: from a start far from the optimum, rejected
steps raise the damping until a step lowers the cost, and the refinement still lands on the optimum.
(Its weights and its minimum are tested in test_robust.py.)"""

from __future__ import annotations

import numpy as np
import pytest
from test_robust import session  # its synthetic sessions (tests/app is on pythonpath)

from calibcoach.app.solve.calibrate import reprojection_residuals, solve
from calibcoach.app.solve.weighted import weighted_refine

from _synthetic import SIZE


def rms(camera, views, rvecs, tvecs) -> float:
    res = np.concatenate(reprojection_residuals(camera, views, rvecs, tvecs))
    return float(np.sqrt(np.mean(np.sum(res**2, axis=1))))


@pytest.mark.parametrize("rotation_off", [0.2, 0.5])
def test_from_poses_far_off_the_damping_finds_the_optimum(rotation_off: float) -> None:
    """Every pose 0.2 or 0.5 rad off and 30% too far: undamped Gauss-Newton steps overshoot (the cost
    rises); the damping grows until one does not, and 15 iterations reach OpenCV's optimum."""
    _rng, _poses, views, _mask = session(8, 0.2, n=10)
    raw = solve(views, SIZE, "pinhole")
    camera, rv, tv = weighted_refine(raw.camera, views, raw.rvecs + rotation_off, raw.tvecs * 1.3, np.ones(len(views)))
    assert rms(camera, views, rv, tv) == pytest.approx(raw.rms_px, rel=1e-4)
    np.testing.assert_allclose(camera.camera_matrix, raw.camera.camera_matrix, atol=0.01)
