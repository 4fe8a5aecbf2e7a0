"""Next-best pose: which candidate pose would cut the expected projection error E the most.

Calibration Wizard and AprilCal choose the next view by the uncertainty it is predicted to
leave; so does calibcoach. A candidate's virtual view (the corners the detector would find at
that pose, through the current intrinsics) is stacked onto the information of the frames kept
so far (the Schur complement with its own pose marginalised, exactly as a real frame would be),
and E is recomputed: E^2 = sigma^2 trace(W S^-1), W the covered region's pixel weight. The noise
sigma cancels in the relative cut, so candidates are ranked before the first full solve too.

While coverage is incomplete, the share of the unmet coverage a candidate would fill weighs in:
filling all of it counts like halving E (`COVERAGE_WORTH`), since E is only measured where the
board has been and the rest of the image is extrapolation.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass

import numpy as np

from calibcoach.app.solve.calibrate import pose_for_view
from calibcoach.app.solve.information import (
    covariance_from_information,
    information_gain,
    schur_update,
    schur_updates,
    view_jacobian,
)
from calibcoach.app.solve.result import View
from calibcoach.coverage.candidates import CandidatePose
from calibcoach.coverage.grid import CoverageMap
from calibcoach.drivers.lens import CameraModel

COVERAGE_WORTH = 0.5  # filling all unmet coverage is worth as much as cutting E by half


@dataclass(frozen=True, slots=True)
class RankedPose:
    candidate: CandidatePose
    error_cut: float  # relative cut of E if a frame at this pose joined, 0..1
    coverage_gain: float  # share of the whole coverage map it would fill, 0..1
    score: float  # what the ranking sorts by (higher first)


def error_cut(information: np.ndarray, weight: np.ndarray, J_intr: np.ndarray, J_pose: np.ndarray) -> tuple[np.ndarray, float]:
    """New information and the relative cut of E = sqrt(trace(W S^-1)) if a view joins.

    Args:
        information: (P, P) float64 S of the frames so far (unit noise).
        weight: (P, P) float64 W (`UncertaintyMap.error_weight`).
        J_intr: (2n, P) float64 the view's intrinsic Jacobian; J_pose (2n, 6) its pose Jacobian.

    Returns:
        (P, P) float64 S with the view, and the cut 1 - E_after / E_before in [0, 1].
    """
    S_new = schur_update(information, J_intr, J_pose)
    return S_new, _cut(float(np.sum(weight * covariance_from_information(information))),
                       float(np.sum(weight * covariance_from_information(S_new))))


def error_cuts(information: np.ndarray, weight: np.ndarray, jacobians: Sequence[tuple[np.ndarray, np.ndarray]]) -> list[float]:
    """`error_cut` of each view's (J_intr, J_pose) joining S on its own, batched (ranking hundreds of candidates)."""
    before = float(np.sum(weight * covariance_from_information(information)))
    after = np.sum(weight * covariance_from_information(schur_updates(information, jacobians)), axis=(-2, -1))
    return [_cut(before, float(a)) for a in after]


def _cut(before: float, after: float) -> float:
    """1 - E_after / E_before from trace(W S^-1) before and after, in [0, 1]; 0 where either is unusable."""
    if not (before > 0 and np.isfinite(after)):
        return 0.0
    return float(max(0.0, 1.0 - np.sqrt(max(after, 0.0) / before)))


def _tilt_and_range(candidate: CandidatePose) -> tuple[float, float, float, float]:
    """(tilt to the line of sight, tilt_x, tilt_y, distance_m) of a frame at the candidate pose, for
    `CoverageMap.contributions` (no PnP: the pose is known)."""
    tilt = float(np.degrees(np.arccos(np.cos(np.radians(candidate.tilt_x_deg)) * np.cos(np.radians(candidate.tilt_y_deg)))))
    return tilt, candidate.tilt_x_deg, candidate.tilt_y_deg, candidate.range_m


def rank_poses(
    camera: CameraModel,
    information: np.ndarray,
    weight: np.ndarray,
    candidates: Sequence[CandidatePose],
    coverage: CoverageMap,
    *,
    board_centre_m: np.ndarray,
    excluded: Collection[tuple] = (),
    use_error: bool = True,
) -> list[RankedPose]:
    """Candidates best first; `excluded` keys (targets that did not register) are left out.

    `use_error` False ranks by coverage alone: before the first solve the full model's information
    is rank deficient and every candidate would "cut E by 99%".

    Ties are broken by the candidate order (position, tilt, range), so the ranking is reproducible.
    """
    deficit = 1.0 - coverage.completeness()
    considered = [c for c in candidates if c.key not in excluded]
    cuts = [0.0] * len(considered)
    if use_error:
        jacobians = [view_jacobian(camera, c.view.object_points_m, c.view.rvec, c.view.tvec) for c in considered]
        projectable = [bool(np.all(np.isfinite(Ji)) and np.all(np.isfinite(Jp))) for Ji, Jp in jacobians]
        considered = [c for c, ok in zip(considered, projectable, strict=True) if ok]
        cuts = error_cuts(information, weight, [j for j, ok in zip(jacobians, projectable, strict=True) if ok])
    gains = np.zeros(len(considered))
    if deficit > 1e-3 and considered:
        gains = coverage.gains(coverage.contributions([c.view.image_points_px for c in considered],
                                                      [_tilt_and_range(c) for c in considered]))
    ranked: list[RankedPose] = []
    for cand, cut, gain in zip(considered, cuts, gains.tolist(), strict=True):
        score = cut + (COVERAGE_WORTH * gain / deficit if deficit > 1e-3 else 0.0)
        ranked.append(RankedPose(cand, cut, gain, score))
    ranked.sort(key=lambda r: -r.score)  # stable: equal scores keep the candidate order
    return ranked


MIN_FILL_GAIN = 0.002  # a reserve frame must cut E^2 by 0.2% to be worth solving with


def fill_from_reserve(camera: CameraModel, information: np.ndarray, weight: np.ndarray | None,
                      reserve: Sequence[tuple[View, float]], budget: int, *,
                      alike: Callable[[View, View], bool], kept: Sequence[View]) -> tuple[list[View], list[View]]:
    """Up to `budget` reserve frames, as (distinct poses, repeats of every pose alike).

    1. Frames that look like nothing already in (`alike`: same place, size and tilt), greedily by
       the cut of E^2 they bring (each pick updates S): poses the live selection passed over.
    2. With budget left, the rest of each hold: the same number of look-alikes for every pose in
       the solve (round-robin, the one nearest in time first), so repeats average each pose's
       noise without shifting weight between poses. Measured on the closed-loop simulator, a
       greedy fill that piled look-alikes onto the most informative poses doubled the true error
       on one seed (0.026 -> 0.056 px) and halved it on another; spread evenly the repeats helped
       on average (bench/guided.py); the covariance counts them for what their residuals share.

    Args:
        reserve: (view, quality) of usable frames not kept live.
        alike: the look-alike test between two views.
        kept: the views already in the solve.
    """
    candidates: list[tuple[View, np.ndarray, np.ndarray]] = []
    repeats: list[View] = []
    for view, quality in reserve:
        if any(alike(view, k) for k in kept):
            repeats.append(view)
            continue
        pose = pose_for_view(camera, view)
        if pose is not None:
            J_intr, J_pose = (np.sqrt(quality) * J for J in view_jacobian(camera, view.object_points_m, *pose))
            if np.all(np.isfinite(J_intr)) and np.all(np.isfinite(J_pose)):
                candidates.append((view, J_intr, J_pose))
    added: list[View] = []
    while candidates and len(added) < budget:
        gains = [information_gain(information, Ji, Jp, weight=weight) for _v, Ji, Jp in candidates]
        best = int(np.argmax([g for _S, g in gains]))
        if gains[best][1] < MIN_FILL_GAIN:
            break
        information = gains[best][0]
        picked = candidates.pop(best)[0]
        added.append(picked)
        repeats += [c[0] for c in candidates if alike(c[0], picked)]
        candidates = [c for c in candidates if not alike(c[0], picked)]
    poses = [*kept, *added]
    distinct = list(added)
    queues = [sorted((r for r in repeats if alike(r, p)), key=lambda r, p=p: abs(r.frame_index - p.frame_index))
              for p in poses]
    taken: set[int] = set()
    while len(added) < budget and any(queues):
        for queue in queues:  # one more repeat for every pose that still has one, in turn
            while queue and queue[0].frame_index in taken:
                queue.pop(0)
            if queue and len(added) < budget:
                repeat = queue.pop(0)
                taken.add(repeat.frame_index)
                added.append(repeat)
    return distinct, added[len(distinct):]
