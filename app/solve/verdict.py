"""The verdict: the method's RMS table, overruled by coverage and projection uncertainty.

RMS reprojection error only says the model fits the frames it saw. A capture of frontal, centred
frames fits beautifully and is still tens of pixels wrong at the edges, so a calibration is
trusted only when the coverage map is (nearly) complete and the projection uncertainty over the
whole image is small; otherwise the grade is "insufficient" whatever the RMS.
"""

from __future__ import annotations

import numpy as np

from calibcoach.app.solve.result import Calibration, UncertaintyMap, Verdict

REFERENCE_DIAGONAL_PX = float(np.hypot(1280, 720))  # the method's thresholds are for ~720p
RMS_TABLE_PX = (0.3, 0.5, 1.0)  # < excellent, < good, < acceptable, else poor
UNCERTAINTY_TARGET_PX = 0.05  # p95 over the covered image at 720p: the stop rule's target
# Beyond this multiple of the target (0.3 px at 720p) the result is not trusted. Not tighter: the
# covariance assumes independent corner noise at the RMS level, and on rendered captures the true
# error came out 4-5x below the prediction (a Monte-Carlo re-solve with independent noise on the
# same geometry matched the prediction, so part of the residual is structure that poses absorb).
UNCERTAINTY_TRUST_FACTOR = 6.0
MIN_COVERAGE_TO_TRUST = 0.85


def resolution_scale(image_size: tuple[int, int]) -> float:
    return float(np.hypot(*image_size)) / REFERENCE_DIAGONAL_PX


def uncertainty_target_px(image_size: tuple[int, int]) -> float:
    """The stop rule's p95 target; it scales with the image diagonal (pixels get smaller)."""
    return UNCERTAINTY_TARGET_PX * max(resolution_scale(image_size), 0.5)


def rms_thresholds_px(image_size: tuple[int, int]) -> tuple[float, float, float]:
    """The method's RMS table, tighter for higher resolutions.

    Sub-pixel corner noise does not grow with resolution, and a higher-resolution camera is bought
    for more precise geometry, so above 720p the bounds shrink with the square root of the
    diagonal ratio (1080p: x0.82, 4K: x0.6, the floor).
    """
    factor = float(np.clip(1.0 / np.sqrt(max(resolution_scale(image_size), 1.0)), 0.6, 1.0))
    return tuple(round(t * factor, 3) for t in RMS_TABLE_PX)  # type: ignore[return-value]


def rms_grade(rms_px: float, thresholds: tuple[float, float, float]) -> str:
    if rms_px < thresholds[0]:
        return "excellent"
    if rms_px < thresholds[1]:
        return "good"
    if rms_px < thresholds[2]:
        return "acceptable"
    return "poor"


def judge(
    calibration: Calibration,
    *,
    coverage_completeness: float,
    coverage_missing: dict[str, list],
    uncertainty: UncertaintyMap,
    image_size: tuple[int, int],
) -> Verdict:
    """Grade a calibration; `trusted` is False when coverage or uncertainty is not good enough."""
    thresholds = rms_thresholds_px(image_size)
    grade_rms = rms_grade(calibration.rms_px, thresholds)
    target = uncertainty_target_px(image_size)
    # Judged where the board was seen: outside it every model extrapolates (uncertainty.png shows
    # how far), and the coverage requirement already insists that region be most of the image.
    p95 = uncertainty.p95_covered_px
    whole = uncertainty.p95_px
    reasons: list[str] = [
        f"RMS reprojection error {calibration.rms_px:.3f} px: {grade_rms} by the method's table "
        f"(< {thresholds[0]} excellent, < {thresholds[1]} good, < {thresholds[2]} acceptable at this resolution)."
    ]
    trusted = True
    if coverage_completeness < MIN_COVERAGE_TO_TRUST:
        trusted = False
        reasons.append(f"Coverage is only {coverage_completeness * 100:.0f}% (needs {MIN_COVERAGE_TO_TRUST * 100:.0f}%): " + _missing_words(coverage_missing))
    elif coverage_completeness < 0.999:
        reasons.append(f"Coverage {coverage_completeness * 100:.0f}%: " + _missing_words(coverage_missing))
    else:
        reasons.append("Coverage complete: all image regions, tilt directions and distances were seen.")
    where = f"over the region the board covered (whole image: {whole:.3f} px)"
    if p95 > UNCERTAINTY_TRUST_FACTOR * target:
        trusted = False
        reasons.append(
            f"Projection uncertainty p95 {where} is {p95:.3f} px, over {UNCERTAINTY_TRUST_FACTOR:g}x the "
            f"{target:.3f} px target: the data does not pin the lens down (worst {float(uncertainty.sigma_px.max()):.2f} px)."
        )
    elif p95 > target:
        reasons.append(f"Projection uncertainty p95 {where} is {p95:.3f} px, above the {target:.3f} px target.")
    else:
        reasons.append(f"Projection uncertainty p95 {where} is {p95:.3f} px, within the {target:.3f} px target.")
    if calibration.dropped_frames:
        reasons.append(f"{len(calibration.dropped_frames)} outlier frames were dropped before the final solve.")
    if not trusted:
        reasons.append("Do not use this calibration: capture the missing views (the guidance says where) and run again.")
        return Verdict("insufficient", False, grade_rms, tuple(reasons), thresholds)
    grade = grade_rms
    if coverage_completeness < 0.999 or p95 > target:
        grade = {"excellent": "good", "good": "acceptable", "acceptable": "poor", "poor": "poor"}[grade_rms]
        reasons.append(f"Graded {grade} rather than {grade_rms}: coverage or uncertainty falls short of the target.")
    return Verdict(grade, True, grade_rms, tuple(reasons), thresholds)


def _missing_words(missing: dict[str, list]) -> str:
    parts = []
    if missing.get("regions"):
        parts.append(f"{len(missing['regions'])} image regions")
    if missing.get("tilts"):
        parts.append("tilts " + ", ".join(str(t).replace("_", " ") for t in missing["tilts"]))
    if missing.get("distances"):
        parts.append("distances " + ", ".join(missing["distances"]))
    return ("missing " + "; ".join(parts) + ".") if parts else "nothing specific missing."
