"""Focus drift, live and replayed: the event goes into the recording, and the replay decides every frame
as the live session did, whether the drift shows in the camera's control reports or only as softness."""

from __future__ import annotations

import json
import threading
from collections.abc import Callable, Iterator
from dataclasses import fields, replace
from pathlib import Path
from types import MappingProxyType

import cv2
import pytest

from calibcoach.app.cli import main
from calibcoach.app.live import PacedSource, run_live
from calibcoach.app.replay import run_replay
from calibcoach.app.session import SessionSettings
from calibcoach.coverage.board import BoardSpec
from calibcoach.drivers.base import Frame, FrameSource, SourceInfo
from calibcoach.drivers.errors import CalibcoachError
from calibcoach.drivers.recording import SESSION_FILE, read_session
from calibcoach.drivers.replay import RecordingSource, open_source

DEMO = "demo_webcam720_careful"
LOCK = {"focus_absolute": 300.0}
MOVED_AT = 60  # of the demo's 120 frames


class FocusSlips(FrameSource):
    """A camera whose frames report their focus; from frame `at` on the lens has moved (`change` applied)."""

    def __init__(self, inner: FrameSource, at: int, change: Callable[[Frame], Frame]) -> None:
        super().__init__()
        self.inner, self.at, self.change = inner, at, change

    @property
    def info(self) -> SourceInfo:
        return replace(self.inner.info, kind="v4l2")  # a camera, not a file: live treats it as one

    def frames(self) -> Iterator[Frame]:
        for n, frame in enumerate(self.inner.frames()):
            frame = replace(frame, index=n, controls=MappingProxyType(dict(LOCK)))
            yield self.change(frame) if n >= self.at else frame


def control_moves(frame: Frame) -> Frame:
    return replace(frame, controls=MappingProxyType({"focus_absolute": 310.0}))


class SoftAfter(FocusSlips):
    """No focus readback; from frame `at` on the person holds the board in view while the lens goes soft
    (the demo's first board frames again, blurred by a gaussian of 1.3 px: ~1.9x the demo's 0.8 px edges,
    still detected; a stronger blur loses the board altogether, so there is nothing left to accept)."""

    BOARD_FRAMES = (0, 1, 2, 6, 7, 8, 9, 14, 15, 16, 21, 22, 23)

    def frames(self) -> Iterator[Frame]:
        early: dict[int, Frame] = {}
        for n, frame in enumerate(self.inner.frames()):
            early.setdefault(n, frame) if n in self.BOARD_FRAMES else None
            if n >= self.at:
                held = early[self.BOARD_FRAMES[(n - self.at) % len(self.BOARD_FRAMES)]]
                frame = replace(frame, image=cv2.GaussianBlur(held.image, (0, 0), 1.3))
            yield replace(frame, index=n, controls=MappingProxyType(dict(LOCK)))


def goes_soft(frame: Frame) -> Frame:  # marks the soft case; SoftAfter does the work
    return frame


class Lockstep(FrameSource):
    """Offers the next frame only once the live loop took the last one (its detection began), so the loop
    drops nothing however loaded the machine is: what it decides does not depend on the load."""

    def __init__(self, inner: FrameSource) -> None:
        super().__init__()
        self.inner = inner
        self._taken: set[int] = set()  # timestamps of the frames the loop took
        self._changed = threading.Condition()

    @property
    def info(self) -> SourceInfo:
        return self.inner.info

    def frames(self) -> Iterator[Frame]:
        lockstep = self

        class Taken(Frame):  # the loop's first use of a frame it took is its grey image, for detection
            def grey(self):
                with lockstep._changed:
                    lockstep._taken.add(self.timestamp_ns)
                    lockstep._changed.notify_all()
                return super().grey()

        for frame in self.inner.frames():
            yield Taken(**{f.name: getattr(frame, f.name) for f in fields(frame) if f.init})
            with self._changed:
                if not self._changed.wait_for(lambda t=frame.timestamp_ns: t in self._taken, timeout=30):
                    raise TimeoutError("the live loop took no frame for 30 s")


def decisions_of(run: Callable[..., object]) -> tuple[list[tuple[int, str]], object]:
    seen: list[tuple[int, str]] = []

    def record(outcome, frame, *rest) -> None:
        seen.append((frame.index, outcome.decision.reason))

    return seen, run(record)


# softness needs 15 frames with a board after the change: the soft case changes earlier
@pytest.mark.parametrize(("change", "at"), [(control_moves, MOVED_AT), (goes_soft, 40)],
                         ids=["control-reads-back-moved", "frames-go-soft"])
def test_a_drift_is_recorded_and_the_replay_decides_every_frame_as_live_did(recordings_dir: Path, tmp_path: Path,
                                                                              change, at: int) -> None:
    board = BoardSpec()
    kind = SoftAfter if change is goes_soft else FocusSlips
    source = Lockstep(kind(open_source(recordings_dir / DEMO), at, change))
    live, (session, stats) = decisions_of(lambda cb: run_live(source, board, SessionSettings(), record=tmp_path / "rec",
                                                              locked_controls=LOCK, on_outcome=cb))
    assert [i for i, _ in live] == list(range(120))  # nothing dropped
    events = read_session(tmp_path / "rec").header["events"]
    assert len(events) == 1 and events[0]["kind"] == "focus_drift"
    noticed = events[0]["frame_index"]
    if change is control_moves:
        assert noticed >= at and "focus_absolute moved from 300 to 310" in stats.focus_drift
    else:  # 15 soft frames with a board; the run starts where the blur began
        assert noticed >= at + 14 and "blurrier" in stats.focus_drift
        assert at <= events[0]["first_bad_index"] <= noticed - 14
    accepted = [i for i, reason in live if reason == "accepted"]
    assert accepted and max(accepted) <= noticed
    assert all(reason in ("focus drift", "no board", "too few corners", "collinear") for i, reason in live if i > noticed)
    assert any(reason == "focus drift" for i, reason in live if i > noticed)

    replayed, _ = decisions_of(lambda cb: run_replay(RecordingSource(tmp_path / "rec"), board, SessionSettings(),
                                                     on_outcome=cb))
    assert replayed == live
    final = session.finish()
    assert all(v.frame_index < events[0]["first_bad_index"] for v in final.calibration.views)
    assert any("Focus drifted" in r for r in final.verdict.reasons)


def test_a_recorded_drift_applies_even_where_the_frames_lost_their_control_reports(recordings_dir: Path,
                                                                                     tmp_path: Path) -> None:
    board = BoardSpec()
    source = FocusSlips(PacedSource(open_source(recordings_dir / DEMO), speed=8.0), MOVED_AT, control_moves)
    live, _ = decisions_of(lambda cb: run_live(source, board, SessionSettings(), record=tmp_path / "rec",
                                               locked_controls=LOCK, on_outcome=cb))  # dropped frames are not recorded
    header = json.loads((tmp_path / "rec" / SESSION_FILE).read_text())
    for entry in header["frames"]:
        entry["controls"] = {}  # an exporter that dropped them: only the stored event is left
    (tmp_path / "rec" / SESSION_FILE).write_text(json.dumps(header))
    replayed, _ = decisions_of(lambda cb: run_replay(RecordingSource(tmp_path / "rec"), board, SessionSettings(),
                                                     on_outcome=cb))
    assert replayed == live


def test_resume_after_a_drift_needs_the_recorded_lock_then_accepts_again_and_replays_identically(
        recordings_dir: Path, tmp_path: Path) -> None:
    board = BoardSpec()
    first = Lockstep(FocusSlips(open_source(recordings_dir / DEMO), 30, control_moves))
    decisions_of(lambda cb: run_live(first, board, SessionSettings(), record=tmp_path / "rec", locked_controls=LOCK,
                                     on_outcome=cb))
    with pytest.raises(CalibcoachError, match="focus_absolute 300 then, 310 now"):
        run_live(FocusSlips(open_source(recordings_dir / DEMO), 0, control_moves), board, SessionSettings(),
                 resume=tmp_path / "rec", locked_controls={"focus_absolute": 310.0})
    again = Lockstep(FocusSlips(open_source(recordings_dir / DEMO), 10**6, control_moves))
    resumed, _ = decisions_of(lambda cb: run_live(again, board, SessionSettings(), resume=tmp_path / "rec",
                                                  locked_controls=LOCK, on_outcome=cb))
    kinds = [e["kind"] for e in read_session(tmp_path / "rec").header["events"]]
    assert kinds == ["focus_drift", "focus_relocked"]
    relocked_at = read_session(tmp_path / "rec").header["events"][1]["frame_index"]
    assert any(reason == "accepted" for i, reason in resumed if i >= relocked_at)
    replayed, _ = decisions_of(lambda cb: run_replay(RecordingSource(tmp_path / "rec"), board, SessionSettings(),
                                                     on_outcome=cb))
    assert replayed == resumed
    code = main(["calibrate", str(tmp_path / "rec"), "--out", str(tmp_path / "out"), "--quiet"])
    verdict = json.loads((tmp_path / "out" / "calibration.json").read_text())["verdict"]
    assert code == (0 if verdict["trusted"] else 3)  # the exit code says whether the result can be trusted
    assert any("Focus drifted" in r for r in verdict["reasons"])
