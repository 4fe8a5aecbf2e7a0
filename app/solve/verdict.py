"""The verdict: the method's RMS table, overruled by coverage and projection uncertainty.

RMS reprojection error only says the model fits the frames it saw. A capture of frontal, centred
frames fits beautifully and is still tens of pixels wrong at the edges, so a calibration is
trusted only when the coverage map is (nearly) complete -- or lacks only views into which the
model's extrapolation is pinned down, by E over the whole image -- and the expected projection
error E where the board was seen is small against the camera's own corner noise; otherwise the
grade is "insufficient" whatever the RMS. A capture that never showed some tilt is judged on E
widened by the most it was seen to read low without one.
"""

from __future__ import annotations

import numpy as np

from calibcoach.app.solve.residual_structure import ResidualStructure
from calibcoach.app.solve.result import Calibration, UncertaintyMap, Verdict

REFERENCE_DIAGONAL_PX = float(np.hypot(1280, 720))  # the method's thresholds are for ~720p
RMS_TABLE_PX = (0.3, 0.5, 1.0)  # < excellent, < good, < acceptable, else poor
# The stop rule's target for E, the expected projection error over the covered region, is set
# against the camera's own corner noise sigma (per coordinate, measured by the solve): at
# E = sigma / 2 the calibration adds sqrt(1 + 1/4) - 1 = 12% to the error of any point this camera
# measures, so better intrinsics would hardly be noticed downstream. E scales with sigma, so this
# asks for a geometry (enough diverse views) rather than a noise level. Bounds, scaled with the
# image diagonal: below 0.02 px at 720p no user would see a difference; 0.05 px at 720p is the
# most a target asks for, so a noisy camera is still held to a useful accuracy -- it then stops
# by diminishing returns and the verdict names the noise as the limit. On the closed-loop
# simulator (webcam, wide, fisheye; bench/guided.py) E/sigma was ~0.8-1.0 after 30 diverse
# frames, so for clean corners the floor decides and the stop is usually diminishing returns.
ERROR_TARGET_SHARE_OF_NOISE = 0.5
ERROR_TARGET_FLOOR_PX = 0.02
ERROR_TARGET_CAP_PX = 0.05
# Not trusted when E is above both 0.2 px at 720p and the corner noise itself: the calibration
# would then add more error to every measurement than the camera's own detection noise does, and
# more than a fifth of the method's "acceptable" RMS bound (1 px). Between the target and this
# bound a calibration is trusted but graded down: a short careful capture (the bundled demo, 13
# distinct holds in 24 s) lands there at E ~0.13 px with a true error of ~0.04 px.
ERROR_TRUST_PX = 0.20
NOISY_CORNERS_PX = 0.3  # corner noise per coordinate above which the verdict names noise as the limit
MIN_COVERAGE_TO_TRUST = 0.85
# ... unless the model pins the missing views down anyway. Coverage stands in for what the data
# determines; where the board never went, the projection there is the model's extrapolation, and
# the solve's covariance says how well that is determined: E over the whole reachable image (not
# just the covered region) is held to the same trust bound as E over the covered region, because a
# point measured there carries that error. Messy renders that never reach a third of the image
# (82-83% coverage) extrapolate to 0.016-0.047 px against the truth over the whole image with E
# there 0.13-0.15 px (bench/results/coverage_trust.md). A missing range is no blind spot for E: in
# the 6 captures of bench/results/coverage_ablation.md that lacked one (never shown, or its views
# taken out) but showed every tilt, E stayed honest (true / E 0.25-1.18, errors 0.011-0.041 px).
# A missing tilt is one: tilted views are what separates focal length from distance (a frontal
# board at twice the distance through twice the focal length looks the same), and without one E
# can read low. In the 95 cases of coverage_ablation.md that lacked a tilt (as captured, or with
# the views of a tilt or range taken out; 29 renders of 10 capture styles), the 75 whose E over the
# whole image was within the trust bound had a true error at most 2.18x their E there (median
# 0.50x; 2.17x over the covered region; shaky s101 without steep_x: 0.037 px against E 0.017; a
# fast-swinging capture without steep_y: 0.175 against 0.123). Such a capture is judged on both E
# widened by 2.5, that worst ratio with a margin, whatever its coverage; the 46 cases this trusts
# had true errors of at most 0.064 px (bench/missing_tilt_factor.py).
MISSING_TILT_E_FACTOR = 2.5


def resolution_scale(image_size: tuple[int, int]) -> float:
    return float(np.hypot(*image_size)) / REFERENCE_DIAGONAL_PX


def error_target_px(noise_px: float, image_size: tuple[int, int]) -> float:
    """The stop rule's target for E (px) from the measured corner noise (see ERROR_TARGET_SHARE_OF_NOISE).

    Example:
        >>> round(error_target_px(0.06, (1280, 720)), 3), round(error_target_px(0.6, (1280, 720)), 3)
        (0.03, 0.05)
    """
    scale = max(resolution_scale(image_size), 0.5)
    return float(np.clip(ERROR_TARGET_SHARE_OF_NOISE * noise_px, ERROR_TARGET_FLOOR_PX * scale, ERROR_TARGET_CAP_PX * scale))


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
    noise_px: float,
    target_px: float | None = None,
    structure: ResidualStructure | None = None,
    reachable_error_px: float | None = None,
) -> Verdict:
    """Grade a calibration; `trusted` is False when coverage or E is not good enough.

    Args:
        noise_px: corner noise per coordinate the solve measured (`robust.noise_sigma_px`).
        target_px: E target; None derives it from `noise_px` (`error_target_px`).
        structure: the residuals' patterns fixed to the board or the image (`residual_structure`);
            a flagged one is named with what to do about it. It does not change the grade: the
            coverage and E say how well the data pins the model down, this says what the model
            had to absorb.
        reachable_error_px: E over every image point a board can be seen in, covered or not
            (`UncertaintyMap.expected_error_where`); None: unknown, and short coverage or a missing tilt is refused.
    """
    thresholds = rms_thresholds_px(image_size)
    grade_rms = rms_grade(calibration.rms_px, thresholds)
    target = error_target_px(noise_px, image_size) if target_px is None else target_px
    E = uncertainty.expected_error_px
    reasons: list[str] = [
        f"RMS reprojection error {calibration.rms_px:.3f} px: {grade_rms} by the method's table "
        f"(< {thresholds[0]} excellent, < {thresholds[1]} good, < {thresholds[2]} acceptable at this resolution)."
    ]
    trust_limit = max(ERROR_TRUST_PX * max(resolution_scale(image_size), 0.5), noise_px)
    coverage_short = coverage_completeness < MIN_COVERAGE_TO_TRUST
    missing_tilts = list(coverage_missing.get("tilts") or [])
    widen = MISSING_TILT_E_FACTOR if missing_tilts else 1.0  # E can read low without a tilt (see the constant)
    judged_E = widen * E
    judged_reach = None if reachable_error_px is None else widen * reachable_error_px
    # views missing that E over the covered region does not speak for: the extrapolation must be pinned down
    needs_extrapolation = coverage_short or bool(missing_tilts)
    extrapolated = needs_extrapolation and judged_reach is not None and judged_reach <= trust_limit
    if coverage_short:
        reasons.append(f"Coverage is only {coverage_completeness * 100:.0f}% ({'below' if extrapolated else 'needs'} "
                       f"{MIN_COVERAGE_TO_TRUST * 100:.0f}%): " + _missing_words(coverage_missing))
    elif coverage_completeness < 0.999:
        reasons.append(f"Coverage {coverage_completeness * 100:.0f}%: " + _missing_words(coverage_missing))
    else:
        reasons.append("Coverage complete: every image region a board can be seen in, all tilt directions and ranges.")
    if missing_tilts:
        reasons.append(
            f"No view showed the {_tilt_words(missing_tilts)} tilt{'s' if len(missing_tilts) > 1 else ''}: tilted views "
            "separate focal length from distance, and without one E has read up to 2.2x low on the bench, so E is "
            f"judged at {widen:g}x its value here.")
    whole = "E over the whole image a board can be seen in"
    if needs_extrapolation and judged_reach is not None:
        said = f"{reachable_error_px:.3f} px" + (f" ({judged_reach:.3f} px as judged)" if missing_tilts else "")
        if extrapolated:
            lead = "The" if missing_tilts else "Every tilt was shown, and the"
            reasons.append(f"{lead} lens model extrapolates into the rest: {whole} is {said}, within the "
                           f"{trust_limit:.3f} px trust bound, so it is trusted; capture those views if you need them "
                           "measured rather than extrapolated.")
        else:
            lead = "The" if missing_tilts else "Every tilt was shown, but the"
            reasons.append(f"{lead} model's extrapolation into the rest is not pinned down: {whole} is {said}, "
                           f"above the {trust_limit:.3f} px trust bound.")
    trusted = extrapolated or not needs_extrapolation
    where = (f"expected projection error E over the region the board covered is {E:.3f} px"
             + (f" ({judged_E:.3f} px as judged)" if missing_tilts else "")
             + f" (p95 worst direction {uncertainty.p95_covered_px:.3f} px, whole image {uncertainty.p95_px:.3f} px)")
    if judged_E > trust_limit:
        trusted = False
        reasons.append(f"The {where}, above {trust_limit:.3f} px (its target is {target:.3f} px): "
                       "the data does not pin the lens down.")
    elif judged_E > target:
        reasons.append(f"The {where}, above its {target:.3f} px target.")
    else:
        reasons.append(f"The {where}, within its {target:.3f} px target.")
    # the board's own error is most of the corner residual: better light would not lower it
    board_limits = structure is not None and structure.board.flagged and structure.board.rms_px**2 >= 0.5 * noise_px**2
    if structure is not None:
        reasons += _structure_words(structure, calibration.camera.model)
    if board_limits and structure is not None:
        reasons.append(
            f"What limits it: the board itself. Of the corner residual of {noise_px:.2f} px per coordinate, "
            f"{structure.board.rms_px:.2f} px repeats at the same board corners (above); light, exposure or focus "
            "will not lower that part."
        )
    elif noise_px > NOISY_CORNERS_PX * max(resolution_scale(image_size), 1.0):
        reasons.append(
            f"What limits it: corner noise of {noise_px:.2f} px per coordinate (a sharp, well-lit board gives < 0.1 px); "
            "more light or a shorter exposure, a focused lens, a larger board or closer views would lower it."
        )
    if calibration.dropped_frames:
        reasons.append(f"{len(calibration.dropped_frames)} outlier frames were dropped before the final solve.")
    if not trusted:
        reasons.append(_what_to_do(coverage_short=needs_extrapolation and not extrapolated, excess=judged_E / trust_limit,
                                   noise_px=noise_px, board_limits=board_limits))
        return Verdict("insufficient", False, grade_rms, tuple(reasons), thresholds)
    grade = grade_rms
    if coverage_completeness < 0.999 or judged_E > target:
        grade = {"excellent": "good", "good": "acceptable", "acceptable": "poor", "poor": "poor"}[grade_rms]
        reasons.append(f"Graded {grade} rather than {grade_rms}: coverage or the expected error falls short of the target.")
    return Verdict(grade, True, grade_rms, tuple(reasons), thresholds)


# A refused capture in which more than this share of the frames that showed the board were
# rejected as moving (smeared within the exposure, or in transit) is told how to hold the board:
# the live hint's share (app/session.py, 60% of the last 30 such frames), over the whole capture.
SMEARED_CAPTURE_SHARE = 0.6
_MIN_BOARD_FRAMES_FOR_ADVICE = 15
_NOT_SHOWING_THE_BOARD = ("no board", "too few corners", "collinear")


def smeared_capture_advice(rejections: dict[str, int], exposure: str = "") -> str | None:
    """What to change when most frames that showed the board were smeared, else None.

    `rejections`: the selector's count per decision ("accepted", "moving", ...); `exposure`: the
    reading's words (coverage/exposure.py), named when known.
    """
    shown = sum(n for reason, n in rejections.items() if reason not in _NOT_SHOWING_THE_BOARD)
    moving = rejections.get("moving", 0)
    if shown < _MIN_BOARD_FRAMES_FOR_ADVICE or moving <= SMEARED_CAPTURE_SHARE * shown:
        return None
    said = f" ({exposure} in this footage)" if exposure.startswith("exposure ~") else ""
    return (f"{moving} of the {shown} frames that showed the board were smeared by its motion: hold it still for a "
            f"second at each pose (rest your elbows); more light lets the camera use a shorter exposure{said}.")


def _what_to_do(*, coverage_short: bool, excess: float, noise_px: float, board_limits: bool = False) -> str:
    """The refusal's last sentence: what would make the next capture trusted.

    With coverage short, the views it lacks (they also bring E down). With coverage enough and E
    over its bound by `excess`, the two things E follows: it falls as one over the square root of
    the number of distinct board poses and in proportion to the corner noise, so either remedy is
    named with the factor it needs (a dim capture that covered what it must is not told to look
    for views it already has). `board_limits`: most of the corner residual is the board's own
    error, so the noise is lowered by a board that matches its spec, not by light.
    """
    if coverage_short:
        return "Do not use this calibration: capture the missing views (the guidance says where) and run again."
    return (f"Do not use this calibration: E must come down {excess:.1f}x. It falls with the square root of the "
            f"number of distinct board poses and in proportion to the corner noise, so "
            f"about {excess * excess:.1f}x as many distinct poses (new holds: the frames of one hold count together), or "
            f"corner noise {excess:.1f}x lower than its {noise_px:.2f} px ("
            + ("most of it is the board's own error: a flat board that matches its spec" if board_limits
               else "more light, a shorter exposure, sharper focus") + "), would do it.")


def _structure_words(structure: ResidualStructure, model: str) -> list[str]:
    """A sentence for a residual pattern fixed to the board, else for one fixed to the image.

    A flawed board, seen from poses that keep it near one place in the image, also leaves a
    pattern in the image; the board is then named alone, as the likelier cause.
    """
    board, image = structure.board, structure.image
    if board.flagged:
        return [
            f"The residuals repeat at the same board corners from pose to pose: {structure.board_rms_mm * 1000:.0f} um "
            f"on the board ({board.rms_px:.2f} px per coordinate) that no pose explains, {board.ratio:.1f}x the variance "
            "noise would leave. The board is not the one the spec describes (not flat, or printed unevenly: stretched "
            "along one side, say), and the lens model absorbs part of it: measure the squares along both sides "
            "(--square-mm, --marker-mm) and mount the print flat (glass, aluminium); more frames will not remove it."
        ]
    if image.flagged:
        return [
            f"The residuals cluster in the image: {image.rms_px:.2f} px per coordinate at the same places whichever "
            f"corner lands there, {image.ratio:.1f}x the variance noise would leave. The {model} model does not follow "
            "this lens everywhere (or a rolling shutter skews a moving board): see residuals.png, and try another "
            "--model."
        ]
    return []


def _tilt_words(tilts: list) -> str:
    """"steep x, bottom away" for ["steep_x", "bottom_away"]."""
    return ", ".join(str(t).replace("_", " ") for t in tilts)


def _missing_words(missing: dict[str, list]) -> str:
    parts = []
    if missing.get("regions"):
        parts.append(f"{len(missing['regions'])} image regions")
    if missing.get("tilts"):
        parts.append("tilts " + _tilt_words(missing["tilts"]))
    if missing.get("distances"):
        parts.append("distances " + ", ".join(missing["distances"]))
    return ("missing " + "; ".join(parts) + ".") if parts else "nothing specific missing."
