"""The board's speed at a frame, which smear and rolling shutter follow: measured across the frame."""

from __future__ import annotations

import numpy as np
import pytest

from calibcoach.app.replay import _Feeder, footage_neighbours
from calibcoach.app.scan import Seen
from calibcoach.app.session import CalibrationSession, SessionSettings
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector, Detection
from calibcoach.coverage.exposure import velocities_across
from calibcoach.drivers.base import Frame
from calibcoach.drivers.lens import CameraModel

from _synthetic import detection_at

CAMERA = CameraModel("pinhole", [[900, 0, 640], [0, 900, 360], [0, 0, 1]], [-0.1, 0.05, 0, 0, 0], (1280, 720))
FRAME_NS = 33_333_333  # 30 fps


def speed_at(before_x: float | None, after_x: float | None, *, gate: bool = True) -> float | None:
    """The session's speed for a board at x = 640 px whose frames before and after show it at those x."""
    here = (detection_at(CAMERA, (640, 360), 0.9), FRAME_NS)
    before = None if before_x is None else (detection_at(CAMERA, (before_x, 360), 0.9), 0)
    after = None if after_x is None else (detection_at(CAMERA, (after_x, 360), 0.9), 2 * FRAME_NS)
    return speed_between(here, before, after, gate=gate)


def speed_between(here, before, after, *, gate: bool = True) -> float | None:
    """The session's speed at `here` from its neighbours (each (detection, timestamp_ns) or None)."""
    session = CalibrationSession(BoardSpec(), CAMERA.image_size, SessionSettings(use_motion_gate=gate))
    return session._motion_px_s(here, before, after, velocities_across(here, before, after))


def test_a_board_at_the_turn_of_a_swing_is_still_at_the_frame() -> None:
    # 4 px away before and after (120 px/s either side): the board stands still at the frame itself
    assert speed_at(636, 636) == pytest.approx(0.0, abs=1.0)


def test_a_steady_move_is_its_speed_and_the_start_of_a_move_half_of_it() -> None:
    assert speed_at(636, 644) == pytest.approx(120.0, rel=0.05)
    # still before, 4 px on after: the exposure's second half smears, its first does not
    assert speed_at(640, 644) == pytest.approx(60.0, rel=0.05)


def test_with_one_neighbour_known_the_one_sided_difference_is_used() -> None:
    assert speed_at(None, 644) == pytest.approx(120.0, rel=0.05)
    assert speed_at(636, None) == pytest.approx(120.0, rel=0.05)
    assert speed_at(None, None) is None
    assert speed_at(636, 644, gate=False) is None  # a folder of photos: no speed at all


def test_the_neighbours_a_replay_saw_win_over_the_frames_judged_either_side() -> None:
    """A replay judges only some frames: those either side of a judged one may lie a hold or a transit
    away, across which a swing reads faster than the board moved at the frame."""
    def judged_speed(*, noted: bool) -> float | None:
        session = CalibrationSession(BoardSpec(), CAMERA.image_size, SessionSettings())
        first = Frame(0, 0, np.zeros((720, 1280), np.uint8))
        session.process(first, detection_at(CAMERA, (600, 360), 0.9))  # judged 5 frames before: 40 px away
        if noted:  # the frames either side in the footage: 1 px away each
            session.note_neighbours(5, (detection_at(CAMERA, (639, 360), 0.9), 4 * FRAME_NS),
                                    (detection_at(CAMERA, (641, 360), 0.9), 6 * FRAME_NS))
        following = (detection_at(CAMERA, (680, 360), 0.9), 10 * FRAME_NS)  # judged 5 frames after
        frame = Frame(5, 5 * FRAME_NS, np.zeros((720, 1280), np.uint8))
        return session.process(frame, detection_at(CAMERA, (640, 360), 0.9), following=following).motion_px_s

    assert judged_speed(noted=False) == pytest.approx(240.0, rel=0.05)  # 80 px over 10 frames
    assert judged_speed(noted=True) == pytest.approx(30.0, rel=0.05)  # 2 px over 2 frames


def _seen(index: int, x: float | None, *, skipped: bool = False) -> Seen:
    detection = Detection.empty() if x is None else detection_at(CAMERA, (x, 360), 0.9)
    return Seen(Frame(index, index * FRAME_NS, np.zeros((720, 1280), np.uint8)), detection, None, None,
                in_transit=skipped, skipped=skipped)


def test_a_replay_measures_a_frame_beside_a_skipped_transit_from_its_other_side() -> None:
    def speed(before: Seen, after: Seen) -> float | None:
        here = (detection_at(CAMERA, (640, 360), 0.9), 5 * FRAME_NS)
        return speed_between(here, *footage_neighbours(before, after))

    assert speed(_seen(4, 638), _seen(6, 644)) == pytest.approx(90.0, rel=0.05)  # across: 6 px in 2 frames
    # the frame after was skipped in transit (never detected): the frame before alone, 2 px in one frame
    assert speed(_seen(4, 638), _seen(6, None, skipped=True)) == pytest.approx(60.0, rel=0.05)
    assert speed(_seen(4, None, skipped=True), _seen(6, 644)) == pytest.approx(120.0, rel=0.05)
    assert speed(_seen(4, None, skipped=True), _seen(6, None, skipped=True)) is None


def test_a_replays_last_frame_is_measured_from_the_frame_before_it_in_the_footage() -> None:
    """The last frame is judged when the footage ends, with no frame after it; its speed comes from
    the frame before it in the footage (as live), not from the frame judged before it, a hold away."""
    def tracked(index: int, x: float) -> Seen:
        return Seen(Frame(index, index * FRAME_NS, np.zeros((720, 1280), np.uint8)),
                    detection_at(CAMERA, (x, 360), 0.9), 0, 0.5)

    # judged at x = 600, then a hold tracked 40 px on (639-640), then the last frame, detected in full at 640
    stream = [_seen(0, 600), tracked(1, 639.0), tracked(2, 639.5), tracked(3, 639.5), _seen(4, 640)]
    speeds: dict[int, float | None] = {}
    feeder = _Feeder(CharucoBoardDetector(BoardSpec()), SessionSettings(), lambda outcome, frame: speeds.update(
        {frame.index: outcome.motion_px_s}), locked_controls={}, focus_events=())
    feeder.run(stream)
    assert set(speeds) == {0, 4}
    assert speeds[4] == pytest.approx(15.0, rel=0.1)  # 0.5 px in one frame; from frame 0: 40 px in 4 frames, 300 px/s
