"""The guide: keeps one concrete target pose up, and changes it when it did not work.

After every change of the data (a frame accepted, new intrinsics) the session hands the guide a
fresh ranking of candidate poses (`app/solve/next_view.py`); the guide shows the best one that
has not failed. A target fails, and is not asked for again, when the board was held at it
(centre, tilts and range within a person's error of it, for `EXECUTED_S`) and nothing was
accepted: the pose could not be registered, whatever the model predicted. A target is also set
aside, until three more frames have been accepted, when the person held the board still
`HOLDS_TO_SET_ASIDE` times since it came up (anywhere: their execution may be further off than
"at the target" allows) or when it has been up for `STALE_S`, without anything accepted: the
person tried and the pose did not register. Counting holds rather than seconds keeps the rule
independent of how fast a person moves; the time limit covers holds the detector never saw. The
rules together keep the same unregistered pose from being asked for three times running.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibcoach.app.solve.next_view import RankedPose
from calibcoach.coverage.guidance import Guidance, Target, sentence_for
from calibcoach.coverage.pose import BoardPose
from calibcoach.drivers.geometry import pose_matrix
from calibcoach.drivers.lens import CameraModel

EXECUTED_S = 0.5  # held at the target this long without an acceptance: the target failed
STALE_S = 3.5  # up this long without any acceptance: set aside (about two holds of a person)
SET_ASIDE_ACCEPTS = 3  # a stale target may come back after this many accepted frames
# "At the target": how far a person's execution may be off (human error is ~4% of the image for
# the centre, ~6 deg per tilt, ~8% in range; these are about twice that).
NEAR_CENTRE = 0.10  # share of the image diagonal
NEAR_TILT_DEG = 15.0
NEAR_RANGE = 0.2  # relative
HOLDS_TO_SET_ASIDE = 2  # still holds (anywhere) after a target came up, none accepted: try another
HOLD_STILL = 0.015  # share of the image diagonal the board centre stays within during a hold (a hand's
# tremor moves it ~0.3% at 0.6 m; a move between poses crosses 10-40% of the image)


@dataclass(frozen=True, slots=True)
class _Shown:
    ranked: RankedPose
    issued_ns: int
    accepted_at_issue: int


class Guide:
    """Chooses the target to show from the session's rankings; see the module docstring."""

    def __init__(self, image_size: tuple[int, int], board_centre_m: np.ndarray) -> None:
        self.image_size = image_size
        self.board_centre_m = np.asarray(board_centre_m, np.float64)
        self.ranking: list[RankedPose] = []
        self.failed: set[tuple] = set()
        self._set_aside: dict[tuple, int] = {}  # key -> accepted count at which it may return
        self._shown: _Shown | None = None
        self._near_since_ns: int | None = None
        self._camera: CameraModel | None = None
        self._accepted = 0
        self._hold: tuple[np.ndarray, int, bool] | None = None  # (centre_px, since_ns, counted) of the current stillness
        self._holds = 0  # holds begun after the shown target came up

    @property
    def excluded(self) -> set[tuple]:
        return self.failed | {k for k, until in self._set_aside.items() if self._accepted < until}

    @property
    def best(self) -> RankedPose | None:
        """The best candidate not excluded (what guidance shows), or None."""
        excluded = self.excluded
        return next((r for r in self.ranking if r.candidate.key not in excluded), None)

    def update(self, ranking: list[RankedPose], camera: CameraModel, *, accepted: int) -> None:
        """A new ranking after the data changed; `accepted` = frames accepted so far."""
        self.ranking, self._camera, self._accepted = ranking, camera, accepted

    def observe(self, timestamp_ns: int, pose: BoardPose | None, *, accepted: int) -> None:
        """One processed frame: the board's pose (None when not seen) and frames accepted so far."""
        self._accepted = accepted
        centre = self._centre_px(pose)  # once per frame, for the hold count and "at the target"
        held_since = self._stillness(timestamp_ns, centre)  # before any target change: a hold goes on across it
        best = self.best
        shown = self._shown
        if best is None:
            self._shown = None
            return
        if shown is None or shown.ranked.candidate.key != best.candidate.key or accepted > shown.accepted_at_issue:
            # a new target, or the data changed under the old one: it starts afresh
            self._shown = _Shown(best, timestamp_ns, accepted)
            self._near_since_ns = None
            self._holds = 0
            return
        key = shown.ranked.candidate.key
        if held_since is not None and held_since > shown.issued_ns:  # a try begun after the target came up
            self._holds += 1
        if pose is not None and self._is_near(pose, centre, shown.ranked):
            self._near_since_ns = timestamp_ns if self._near_since_ns is None else self._near_since_ns
            if timestamp_ns - self._near_since_ns >= EXECUTED_S * 1e9:
                self.failed.add(key)
        else:
            self._near_since_ns = None
        if key not in self.failed and (timestamp_ns - shown.issued_ns >= STALE_S * 1e9
                                       or self._holds >= HOLDS_TO_SET_ASIDE):
            self._set_aside[key] = accepted + SET_ASIDE_ACCEPTS
        if key in self.excluded:
            self._shown = None
            self.observe(timestamp_ns, None, accepted=accepted)  # show the next best at once

    def _centre_px(self, pose: BoardPose | None) -> np.ndarray | None:
        """Where the board's centre shows through the current intrinsics ((2,) px), or None."""
        if pose is None or self._camera is None:
            return None
        return self._camera.project((pose_matrix(pose.rvec) @ self.board_centre_m + pose.tvec).reshape(1, 3))[0]

    def _stillness(self, timestamp_ns: int, centre: np.ndarray | None) -> int | None:
        """When the board has just stayed put for EXECUTED_S: when that hold began (once per hold), else None."""
        if centre is None or not np.all(np.isfinite(centre)):
            self._hold = None
            return None
        limit = HOLD_STILL * float(np.hypot(*self.image_size))
        if self._hold is None or np.linalg.norm(centre - self._hold[0]) > limit:
            self._hold = (centre, timestamp_ns, False)
            return None
        anchor, since, counted = self._hold
        if counted or timestamp_ns - since < EXECUTED_S * 1e9:
            return None
        self._hold = (anchor, since, True)
        return since

    def _is_near(self, pose: BoardPose, centre_px: np.ndarray | None, ranked: RankedPose) -> bool:
        cand = ranked.candidate
        if centre_px is None:
            return False
        diag = float(np.hypot(*self.image_size))
        return bool(
            np.all(np.isfinite(centre_px))
            and np.linalg.norm(centre_px - np.asarray(cand.centre_px)) <= NEAR_CENTRE * diag
            and abs(pose.tilt_x_deg - cand.tilt_x_deg) <= NEAR_TILT_DEG
            and abs(pose.tilt_y_deg - cand.tilt_y_deg) <= NEAR_TILT_DEG
            and abs(pose.distance_m / cand.range_m - 1.0) <= NEAR_RANGE
        )

    def guidance(self, *, done: bool, hint: str = "") -> Guidance:
        """The instruction to show now; `hint` says how to hold the board when the frames ask for it."""
        if done:
            return Guidance("Done: hold on, calibrating.", None, "the stop rule is met")
        best = self.best
        if best is None or self._camera is None:
            return Guidance("Hold the board up in front of the camera, facing it, about an arm's length away.",
                            None, "no board seen yet", hint)
        target = target_of(best, self._camera, self.board_centre_m)
        why = f"cuts the expected error by {best.error_cut * 100:.0f}%"
        if best.coverage_gain > 0:
            why += f", fills {best.coverage_gain * 100:.1f}% of the coverage"
        return Guidance(sentence_for(target, self.image_size), target, why, hint)


def target_of(ranked: RankedPose, camera: CameraModel, board_centre_m: np.ndarray) -> Target:
    """The public Target of a ranked candidate: pose, tilts, range and the outline in the image."""
    cand = ranked.candidate
    v = cand.view
    R = pose_matrix(v.rvec)
    sq = board_centre_m[:2] * 2.0  # (width, height) of the chessboard area
    corners = np.array([[0, 0, 0], [sq[0], 0, 0], [sq[0], sq[1], 0], [0, sq[1], 0]], np.float64)
    outline = camera.project(corners @ R.T + v.tvec)
    return Target(centre_px=cand.centre_px, rvec=v.rvec.copy(), tvec_m=v.tvec.copy(), tilt_x_deg=cand.tilt_x_deg,
                  tilt_y_deg=cand.tilt_y_deg, distance_m=cand.range_m, outline_px=outline)
