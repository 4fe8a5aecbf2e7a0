"""The accuracy bench's expert reference (bench/mrcal_reference.py): mrcal's scoring and solve, checked.

Runs Debian's mrcal with /usr/bin/python3 (never the venv); skipped where it is not installed.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from calibcoach.app.export.sfm import write_mrcal
from calibcoach.app.solve.compare import projection_difference
from calibcoach.app.solve.uncertainty import covered_region_mask
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector
from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.recording import read_truth
from calibcoach.drivers.replay import open_source

ROOT = Path(__file__).resolve().parents[2]
DEMO = ROOT / "recordings" / "demo_webcam720_careful"
GRID = (32, 18)


def _bench():
    """bench/mrcal_reference.py as a module (bench code is not part of the package)."""
    spec = importlib.util.spec_from_file_location("mrcal_reference", ROOT / "bench" / "mrcal_reference.py")
    module = sys.modules.get("mrcal_reference")
    if module is None:
        module = importlib.util.module_from_spec(spec)
        sys.modules["mrcal_reference"] = module  # dataclasses look their module up there
        spec.loader.exec_module(module)
    if why := module.mrcal_missing():
        pytest.skip(f"{why} (.ci/run installs python3-mrcal and mrcal)")
    return module


def test_mrcal_scoring_agrees_with_projection_difference_and_mrcal_solves_the_demo(tmp_path: Path) -> None:
    bench = _bench()
    truth = read_truth(DEMO).camera
    # an OpenCV5 estimate a little off the truth, written as mrcal reads it: both scorers must agree
    K = truth.camera_matrix.copy()
    K[0, 0] *= 1.002
    K[0, 2] += 1.5
    dist = np.asarray(truth.dist_coeffs, float) + [0.004, -0.002, 0.0003, 0.0, 0.001]
    estimate = CameraModel("pinhole", K, dist, truth.image_size)
    (path,) = write_mrcal(tmp_path / "export", estimate)
    mask = np.zeros((GRID[1], GRID[0]), bool)
    mask[2:15, 3:27] = True
    for m in (None, mask):
        expected = projection_difference(truth, estimate, grid=GRID, mask=m).rms_px
        assert expected > 0.3  # a difference worth measuring
        assert bench.mrcal_error_vs_truth(truth, path, m, GRID) == pytest.approx(expected, abs=1e-3)

    # mrcal-calibrate-cameras on the recording's detected corners (partial views included)
    detector = CharucoBoardDetector(BoardSpec())
    views = [(f.index, d) for f in open_source(DEMO) if (d := detector.detect(f.grey())).corner_count >= 6]
    solution = bench.solve_with_mrcal([d for _, d in views], BoardSpec(), truth.image_size, "pinhole", tmp_path / "mrcal",
                                      names=[f"frame{i:06d}" for i, _ in views])
    assert not solution.error, f"mrcal failed: {solution.error}\n{solution.log[-2000:]}"
    assert solution.lensmodel == "LENSMODEL_OPENCV5"
    assert solution.rms_px < 0.1 and solution.outliers < 0.01 * solution.points
    covered = covered_region_mask(truth.image_size, [d.corners_px for _, d in views], GRID)
    error = bench.mrcal_error_vs_truth(truth, solution.cameramodel, covered, GRID)
    assert error < 0.1, f"mrcal's calibration is {error:.3f} px from the truth over the covered image"
