"""The verdict at every boundary of the method's RMS table and of its trust rule.

`judge` reads a calibration's RMS, the coverage, the expected projection error E and the corner
noise; here each is set directly (a Calibration and an UncertaintyMap with known numbers), so each
grade and each reason sentence can be checked to appear when, and only when, its condition holds.
"""

from __future__ import annotations

import numpy as np
import pytest

from calibcoach.app.solve.result import Calibration, DroppedFrame, UncertaintyMap
from calibcoach.app.solve.verdict import (
    ERROR_TRUST_PX,
    MIN_COVERAGE_TO_TRUST,
    MISSING_TILT_E_FACTOR,
    NOISY_CORNERS_PX,
    error_target_px,
    judge,
    resolution_scale,
    rms_grade,
    rms_thresholds_px,
    smeared_capture_advice,
)
from calibcoach.drivers.lens import CameraModel

SIZE = (1280, 720)
MISSING = {"regions": [(0, 0, 0.2), (3, 5, 0.1)], "tilts": ["top_away", "steep_x"], "distances": ["far"]}
EVERY_TILT_SHOWN = {**MISSING, "tilts": []}  # a missing tilt has a rule of its own (the last tests of the trust rule)


def calibration(rms_px: float, dropped: int = 0) -> Calibration:
    return Calibration(
        camera=CameraModel.from_fov(SIZE, 70.0), rms_px=rms_px, views=(), rvecs=np.zeros((0, 3)), tvecs=np.zeros((0, 3)),
        residuals_px=(), per_view_rms_px=np.zeros(0), intrinsic_names=(), intrinsic_covariance=np.zeros((0, 0)),
        dropped_frames=tuple(DroppedFrame(i, "test") for i in range(dropped)),
    )


def umap(E: float, p95_covered: float | None = None, p95: float | None = None) -> UncertaintyMap:
    """A 4 x 8 map whose covered half has expected error E everywhere (the rest 10x)."""
    covered = np.zeros((4, 8), bool)
    covered[:, :4] = True
    error = np.where(covered, E, 10 * E)
    sigma = np.where(covered, E if p95_covered is None else p95_covered, E if p95 is None else p95)
    return UncertaintyMap(np.arange(8.0), np.arange(4.0), sigma, covered, error, np.eye(2))


def verdict(rms=0.2, coverage=1.0, E=0.01, noise=0.1, *, size=SIZE, target=None, dropped=0, missing=None):
    return judge(calibration(rms, dropped), coverage_completeness=coverage, coverage_missing=EVERY_TILT_SHOWN if missing is None else missing,
                 uncertainty=umap(E), image_size=size, noise_px=noise, target_px=target)


def has(v, fragment: str) -> bool:
    return any(fragment in r for r in v.reasons)


# --- the RMS table ------------------------------------------------------------------------------


@pytest.mark.parametrize(("rms", "grade"), [
    (0.0, "excellent"), (0.2999, "excellent"), (0.3, "good"), (0.3001, "good"), (0.4999, "good"), (0.5, "acceptable"),
    (0.9999, "acceptable"), (1.0, "poor"), (1.0001, "poor"), (7.0, "poor"),
])
def test_rms_grade_at_each_boundary(rms: float, grade: str) -> None:
    v = verdict(rms=rms)
    assert v.rms_grade == grade and v.grade == grade and v.trusted  # full coverage, E at target: the table decides
    assert v.reasons[0] == (f"RMS reprojection error {rms:.3f} px: {grade} by the method's table "
                            "(< 0.3 excellent, < 0.5 good, < 1.0 acceptable at this resolution).")
    assert v.rms_thresholds_px == (0.3, 0.5, 1.0)


def test_rms_thresholds_shrink_with_resolution() -> None:
    assert rms_thresholds_px((1280, 720)) == (0.3, 0.5, 1.0)
    assert rms_thresholds_px((640, 480)) == (0.3, 0.5, 1.0)  # never looser than the method's table
    f = 1 / np.sqrt(1.5)  # 1080p: 1.5x the 720p diagonal
    assert rms_thresholds_px((1920, 1080)) == (round(0.3 * f, 3), round(0.5 * f, 3), round(1.0 * f, 3)) == (0.245, 0.408, 0.816)
    assert rms_thresholds_px((3840, 2160)) == (0.18, 0.3, 0.6)  # 4K: the 0.6 floor
    assert rms_thresholds_px((7680, 4320)) == (0.18, 0.3, 0.6)
    assert rms_grade(0.25, rms_thresholds_px((1920, 1080))) == "good"
    assert verdict(rms=0.25, size=(1920, 1080)).rms_grade == "good"
    assert verdict(rms=0.25).rms_grade == "excellent"


def test_resolution_scale_is_the_diagonal_ratio() -> None:
    assert resolution_scale((1280, 720)) == pytest.approx(1.0)
    assert resolution_scale((2560, 1440)) == pytest.approx(2.0)
    assert resolution_scale((640, 360)) == pytest.approx(0.5)


# --- the E target -------------------------------------------------------------------------------


@pytest.mark.parametrize(("noise", "size", "target"), [
    (0.06, (1280, 720), 0.03),  # half the noise
    (0.02, (1280, 720), 0.02),  # floor 0.02 px at 720p
    (0.039, (1280, 720), 0.02),
    (0.041, (1280, 720), 0.0205),
    (0.099, (1280, 720), 0.0495),
    (0.6, (1280, 720), 0.05),  # cap 0.05 px at 720p
    (0.6, (2560, 1440), 0.10),  # bounds scale with the diagonal
    (0.01, (2560, 1440), 0.04),
    (0.6, (320, 180), 0.025),  # ... but never below half the 720p ones
    (0.01, (320, 180), 0.01),
])
def test_error_target_is_half_the_noise_within_its_bounds(noise: float, size, target: float) -> None:
    assert error_target_px(noise, size) == pytest.approx(target, rel=1e-9)


# --- the trust rule -----------------------------------------------------------------------------


def test_coverage_below_its_bound_is_not_trusted_whatever_the_rms() -> None:
    low = verdict(rms=0.1, coverage=MIN_COVERAGE_TO_TRUST - 0.001, missing=MISSING)
    assert not low.trusted and low.grade == "insufficient" and low.rms_grade == "excellent"
    assert has(low, "Coverage is only 85% (needs 85%): missing 2 image regions; tilts top away, steep x; distances far.")
    assert low.reasons[-1].startswith("Do not use this calibration")
    at = verdict(rms=0.1, coverage=MIN_COVERAGE_TO_TRUST)
    assert at.trusted and not has(at, "Coverage is only") and not has(at, "Do not use")
    assert has(at, "Coverage 85%: missing 2 image regions")
    assert at.grade == "good"  # incomplete coverage grades one step down
    assert has(at, "Graded good rather than excellent: coverage or the expected error falls short of the target.")


REGIONS_ONLY = {"regions": [(0, 5, 0.0), (1, 5, 0.0), (2, 5, 0.0)], "tilts": [], "distances": []}


def test_missing_regions_or_a_range_the_model_extrapolates_into_within_the_trust_bound_are_trusted() -> None:
    """A capture that never reached some image regions but showed every tilt is judged by E over the whole image:
    the model's extrapolation into the regions is held to the trust bound E over the covered region is."""
    def short(whole: float | None, missing=REGIONS_ONLY, noise=0.05):
        return judge(calibration(0.1), coverage_completeness=0.82, coverage_missing=missing, uncertainty=umap(0.05),
                     image_size=SIZE, noise_px=noise, reachable_error_px=whole)
    at = short(ERROR_TRUST_PX)
    assert at.trusted and at.grade == "good" and at.rms_grade == "excellent"  # graded down: coverage short, E above 0.025
    assert has(at, "Coverage is only 82% (below 85%): missing 3 image regions.")
    assert has(at, "Every tilt was shown, and the lens model extrapolates into the rest: E over the whole image a board "
                   "can be seen in is 0.200 px, within the 0.200 px trust bound, so it is trusted")
    assert not has(at, "Do not use")
    above = short(ERROR_TRUST_PX + 1e-4)
    assert not above.trusted and above.grade == "insufficient"
    assert has(above, "Every tilt was shown, but the model's extrapolation into the rest is not pinned down: E over "
                      "the whole image a board can be seen in is 0.200 px, above the 0.200 px trust bound.")
    assert above.reasons[-1].startswith("Do not use this calibration: capture the missing views")
    assert short(0.39, noise=0.4).trusted and not short(0.41, noise=0.4).trusted  # the bound is the noise when larger
    assert not short(None).trusted  # no whole-image E: short coverage is refused as before
    # a range missing (the fast-swinging captures never hold the board near) is judged the same way: with every tilt
    # shown E stays honest without it (bench/results/coverage_ablation.md)
    near_missing = short(0.1, missing={**REGIONS_ONLY, "distances": ["near"]})
    assert near_missing.trusted and has(near_missing, "missing 3 image regions; distances near.")
    assert has(near_missing, "Every tilt was shown, and the lens model extrapolates")
    assert not short(ERROR_TRUST_PX + 1e-4, missing={**REGIONS_ONLY, "distances": ["near"]}).trusted
    # a tilt missing: judged on E widened (the next test), so a whole-image E at the bound no longer passes
    assert not short(ERROR_TRUST_PX, missing={**REGIONS_ONLY, "tilts": ["steep_x"]}).trusted


def test_a_missing_tilt_is_judged_on_E_widened_by_the_most_it_read_low() -> None:
    """Without some tilt E has read up to 2.2x low on the bench, so both E over the covered region and E over
    the whole image are judged at MISSING_TILT_E_FACTOR times their value, whatever the coverage."""
    lacking = {**REGIONS_ONLY, "tilts": ["steep_x", "bottom_away"]}

    def judged(coverage: float, E: float, whole: float | None, missing=lacking):
        return judge(calibration(0.1), coverage_completeness=coverage, coverage_missing=missing, uncertainty=umap(E),
                     image_size=SIZE, noise_px=0.05, reachable_error_px=whole)
    bound = ERROR_TRUST_PX / MISSING_TILT_E_FACTOR
    at = judged(0.7, 0.04, bound)
    assert at.trusted and at.grade == "good" and at.rms_grade == "excellent"
    assert has(at, "No view showed the steep x, bottom away tilts: tilted views separate focal length from distance, "
                   "and without one E has read up to 2.2x low on the bench, so E is judged at 2.5x its value here.")
    assert has(at, "The lens model extrapolates into the rest: E over the whole image a board can be seen in is "
                   "0.080 px (0.200 px as judged), within the 0.200 px trust bound, so it is trusted")
    assert has(at, "covered is 0.040 px (0.100 px as judged)") and not has(at, "Every tilt was shown")
    above = judged(0.7, 0.04, bound + 1e-4)
    assert not above.trusted and above.grade == "insufficient"
    assert has(above, "The model's extrapolation into the rest is not pinned down: E over the whole image a board can "
                      "be seen in is 0.080 px (0.200 px as judged), above the 0.200 px trust bound.")
    assert above.reasons[-1].startswith("Do not use this calibration: capture the missing views")
    # E over the covered region is widened too
    assert judged(0.7, bound, bound).trusted and not judged(0.7, bound + 1e-4, bound).trusted
    # with enough coverage a missing tilt is judged the same way (it was trusted on E alone before)
    assert judged(0.9, 0.04, bound).trusted and not judged(0.9, 0.04, bound + 1e-4).trusted
    assert not judged(0.9, 0.04, None).trusted  # no whole-image E: refused
    one = judged(0.9, 0.04, bound, missing={**REGIONS_ONLY, "tilts": ["steep_y"]})
    assert has(one, "No view showed the steep y tilt: ")
    # every tilt shown: E as it is
    assert judged(0.7, 0.04, bound + 1e-4, missing=REGIONS_ONLY).trusted
    assert judged(0.9, 0.04, None, missing=REGIONS_ONLY).trusted


def test_expected_error_where_is_the_rms_over_the_marked_points() -> None:
    m = umap(0.05)  # covered half 0.05 px, the rest 0.5
    assert m.expected_error_where(m.covered) == pytest.approx(0.05)
    assert m.expected_error_where(np.ones((4, 8), bool)) == pytest.approx(np.sqrt((0.05**2 + 0.5**2) / 2))
    assert np.isnan(m.expected_error_where(np.zeros((4, 8), bool)))


def test_complete_coverage_is_said_so() -> None:
    full = verdict(coverage=0.999)
    assert has(full, "Coverage complete: every image region") and not has(full, "Coverage 99")
    assert full.grade == "excellent" and not has(full, "Graded")
    almost = verdict(coverage=0.9989)
    assert has(almost, "Coverage 100%: missing") and not has(almost, "Coverage complete") and almost.grade == "good"


def test_missing_words() -> None:
    assert has(verdict(coverage=0.5, missing={}), "Coverage is only 50% (needs 85%): nothing specific missing.")
    assert has(verdict(coverage=0.5, missing={"tilts": ["left_away"]}), "(needs 85%): missing tilts left away.")
    assert has(verdict(coverage=0.9, missing={"regions": [(1, 1, 0.0)], "distances": ["near", "far"]}),
               "Coverage 90%: missing 1 image regions; distances near, far.")


@pytest.mark.parametrize("noise", [0.05, 0.1])
def test_E_above_the_trust_bound_is_not_trusted(noise: float) -> None:
    """Trusted up to E = 0.2 px at 720p (or the corner noise, if larger), whatever the RMS and coverage."""
    target = error_target_px(noise, SIZE)
    above = verdict(rms=0.1, coverage=1.0, E=ERROR_TRUST_PX + 1e-4, noise=noise)
    assert not above.trusted and above.grade == "insufficient" and above.rms_grade == "excellent"
    assert has(above, f"expected projection error E over the region the board covered is {ERROR_TRUST_PX + 1e-4:.3f} px")
    assert has(above, f"above 0.200 px (its target is {target:.3f} px): the data does not pin the lens down.")
    assert above.reasons[-1].startswith("Do not use this calibration")
    at = verdict(rms=0.1, coverage=1.0, E=ERROR_TRUST_PX, noise=noise)
    assert at.trusted and at.grade == "good" and not has(at, "does not pin the lens down")
    assert has(at, f"above its {target:.3f} px target.")
    assert has(at, "Graded good rather than excellent")


def test_a_refusal_with_enough_coverage_names_poses_and_noise_not_missing_views() -> None:
    """A dim capture that covered what it must is told what E follows, with the factor each remedy needs."""
    v = verdict(rms=0.2, coverage=1.0, E=0.3, noise=0.14)  # E 1.5x its 0.2 px bound
    assert not v.trusted
    last = v.reasons[-1]
    assert last.startswith("Do not use this calibration: E must come down 1.5x.")
    assert "about 2.2x as many distinct poses" in last and "corner noise 1.5x lower than its 0.14 px" in last
    assert "missing views" not in last
    short = verdict(rms=0.2, coverage=0.5, E=0.3, noise=0.14)  # coverage short as well: the views come first
    assert short.reasons[-1] == "Do not use this calibration: capture the missing views (the guidance says where) and run again."


def test_the_trust_bound_is_the_noise_when_the_noise_is_larger() -> None:
    v = verdict(rms=0.8, E=0.35, noise=0.4)
    assert v.trusted and v.grade == "poor"  # acceptable by the table, one down for E above its target
    assert has(v, "above its 0.050 px target.") and not has(v, "does not pin")
    v = verdict(rms=0.8, E=0.41, noise=0.4)
    assert not v.trusted and has(v, "above 0.400 px (its target is 0.050 px)")


def test_the_trust_bound_scales_with_resolution() -> None:
    big = (2560, 1440)
    assert verdict(E=0.39, size=big).trusted and not verdict(E=0.41, size=big).trusted  # 0.4 px at 2x the diagonal
    small = (320, 180)  # never below half the 720p bound
    assert verdict(E=0.099, size=small).trusted and not verdict(E=0.101, size=small).trusted


def test_E_at_or_within_its_target() -> None:
    v = verdict(E=0.05, noise=0.1)  # the target is 0.05
    assert has(v, "within its 0.050 px target.") and v.grade == "excellent" and not has(v, "Graded")
    v = verdict(E=0.0501, noise=0.1)
    assert has(v, "above its 0.050 px target.") and v.grade == "good"
    v = verdict(E=0.03, noise=0.1, target=0.02)  # a target given overrides the one from the noise
    assert has(v, "above its 0.020 px target.") and v.grade == "good"
    v = verdict(E=0.03, noise=0.02, target=0.04)
    assert has(v, "within its 0.040 px target.") and v.grade == "excellent"


def test_reasons_carry_the_maps_percentiles() -> None:
    v = judge(calibration(0.2), coverage_completeness=1.0, coverage_missing={}, uncertainty=umap(0.01, 0.034, 0.5),
              image_size=SIZE, noise_px=0.1)
    assert has(v, "(p95 worst direction 0.034 px, whole image 0.500 px)")


@pytest.mark.parametrize(("grade", "rms", "down"), [("excellent", 0.1, "good"), ("good", 0.4, "acceptable"),
                                                    ("acceptable", 0.7, "poor"), ("poor", 2.0, "poor")])
def test_short_of_the_target_grades_one_step_down(grade: str, rms: float, down: str) -> None:
    v = verdict(rms=rms, E=0.1, noise=0.1)
    assert v.trusted and v.rms_grade == grade and v.grade == down
    assert has(v, f"Graded {down} rather than {grade}") and not has(v, "Do not use")


def test_noisy_corners_are_named_as_the_limit() -> None:
    limit = NOISY_CORNERS_PX
    assert not has(verdict(noise=limit), "What limits it")
    v = verdict(noise=limit + 0.001, E=0.01)
    assert has(v, f"What limits it: corner noise of {limit + 0.001:.2f} px per coordinate")
    big = (2560, 1440)  # the bound grows with resolution above 720p...
    assert not has(verdict(noise=0.59, size=big), "What limits it") and has(verdict(noise=0.61, size=big), "What limits it")
    small = (640, 360)  # ...but does not shrink below it
    assert not has(verdict(noise=0.29, size=small), "What limits it") and has(verdict(noise=0.31, size=small), "What limits it")


def test_dropped_frames_are_counted() -> None:
    assert has(verdict(dropped=3), "3 outlier frames were dropped before the final solve.")
    assert not has(verdict(dropped=0), "outlier frames")


def test_a_good_calibration_says_only_what_holds() -> None:
    v = verdict(rms=0.1, coverage=1.0, E=0.01, noise=0.05)
    assert v.trusted and v.grade == "excellent"
    assert len(v.reasons) == 3  # the table, the coverage, E: nothing missing, nothing to do
    for absent in ("Coverage is only", "does not pin", "above its", "What limits it", "outlier frames", "Graded", "Do not use"):
        assert not has(v, absent), absent


def test_a_mostly_smeared_capture_is_told_how_to_hold_the_board() -> None:
    # a fast 31 ms messy render: 38 of the 54 frames that showed the board were moving
    counts = {"accepted": 11, "no board": 373, "too few corners": 40, "collinear": 4, "moving": 38, "duplicate": 5}
    advice = smeared_capture_advice(counts, "exposure ~31 ms (+-4%) read off 50 moving frames' edges")
    assert advice is not None and advice.startswith("38 of the 54 frames") and "rest your elbows" in advice
    assert "exposure ~31 ms" in advice and "shorter exposure" in advice
    assert "exposure" not in smeared_capture_advice(counts, "exposure unknown (16 frames ...)").split("shorter exposure")[1]
    # held well: most frames that showed the board were taken or look-alikes; and too few to say
    assert smeared_capture_advice({**counts, "moving": 20}) is None
    assert smeared_capture_advice({"accepted": 3, "moving": 9}) is None
