"""The guide changes a target that did not register: after two still holds anywhere, or one held at it."""

from __future__ import annotations

import numpy as np

import calibcoach
from calibcoach.app.guide import Guide
from calibcoach.app.solve.next_view import RankedPose
from calibcoach.coverage.candidates import candidate_poses, ranges_for
from calibcoach.coverage.pose import BoardPose
from calibcoach.coverage.virtual_view import BoardGeometry
from calibcoach.drivers.geometry import pose_matrix
from calibcoach.drivers.sim import LENSES

CAMERA = LENSES["webcam720"]
GEOMETRY = BoardGeometry.of(calibcoach.BoardSpec())
FPS = 10


def guide_with_targets() -> Guide:
    candidates = candidate_poses(CAMERA, GEOMETRY, ranges_for(CAMERA, GEOMETRY))
    guide = Guide(CAMERA.image_size, GEOMETRY.centre_m)
    ranking = [RankedPose(c, 0.5 - 0.001 * i, 0.0, 0.5 - 0.001 * i) for i, c in enumerate(candidates)]
    guide.update(ranking, CAMERA, accepted=7)
    return guide


def board_at(pixel: tuple[float, float], distance_m: float = 0.7, tilt_y_deg: float = 0.0) -> BoardPose:
    """A board whose centre shows at `pixel`, `distance_m` away, turned about the vertical axis."""
    R = pose_matrix(np.radians([0.0, tilt_y_deg, 0.0]))
    ray = CAMERA.unproject(np.asarray(pixel, float).reshape(1, 2))[0]
    tvec = ray / np.linalg.norm(ray) * distance_m - R @ GEOMETRY.centre_m
    rvec = np.radians([0.0, tilt_y_deg, 0.0])
    return BoardPose(rvec, tvec, abs(tilt_y_deg), 0.0, tilt_y_deg, distance_m, np.asarray(pixel, float), 0.3, 0.05)


def live_through(guide: Guide, t_s: float, seconds: float, pose_at) -> float:
    """Feed `seconds` of frames at FPS, the pose from `pose_at(t)`; returns the end time."""
    for k in range(int(round(seconds * FPS))):
        t = t_s + k / FPS
        guide.observe(int(t * 1e9), pose_at(t), accepted=7)
    return t_s + seconds


def far_from(target_px, w=CAMERA.image_size[0], h=CAMERA.image_size[1]) -> tuple[float, float]:
    """A spot well away from the target (beyond "at the target"), so only the hold count can act."""
    x, y = target_px
    return (w * 0.8 if x < w / 2 else w * 0.2, h * 0.75 if y < h / 2 else h * 0.25)


def test_two_still_holds_without_a_registration_change_the_target_one_does_not() -> None:
    guide = guide_with_targets()
    guide.observe(0, None, accepted=7)  # the first target comes up
    first = guide.best.candidate.key
    spot_a, spot_b = far_from(guide.best.candidate.centre_px), None
    t = live_through(guide, 0.1, 1.0, lambda t: board_at(spot_a))  # hold 1 (1 s, beyond EXECUTED_S)
    assert guide.best.candidate.key == first  # one hold anywhere: the person may still be on the way
    spot_b = (spot_a[0], CAMERA.image_size[1] - spot_a[1])
    t = live_through(guide, t, 0.4, lambda t: board_at(tuple(np.add(spot_a, np.subtract(spot_b, spot_a) * (t % 1)))))
    live_through(guide, t, 1.0, lambda t: board_at(spot_b))  # hold 2, well under STALE_S since the target came up
    assert guide.best.candidate.key != first


def test_a_hold_that_began_before_the_target_came_up_is_not_counted() -> None:
    guide = guide_with_targets()
    spot = far_from(guide.best.candidate.centre_px)  # the target that will come up: the ranking's first
    live_through(guide, 0.0, 1.0, lambda t: board_at(spot))  # already holding when it appears
    first = guide.best.candidate.key
    t = live_through(guide, 1.0, 1.0, lambda t: board_at(spot))  # the same stillness goes on: not a new try
    other = (spot[0], CAMERA.image_size[1] - spot[1])
    live_through(guide, t, 1.0, lambda t: board_at(other))  # one real try: not yet enough to give up on the target
    assert guide.best.candidate.key == first
