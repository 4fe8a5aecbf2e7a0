"""Focus drift: notice that the lens moved since focus was locked, the same way live and in replay.

A calibration holds for one focus (and zoom) setting: frames taken after the lens moved belong to
another camera. Two signs are watched, both taken from what a recording keeps, so a replay of a
recording reaches the very same decision at the very same frame as the live session did:

- a focus control the driver reports with every frame (V4L2 `focus_absolute`, DepthAI
  `lens_position`, a VISCA position) reads back different from the value locked at the start;
- the frames go soft: 15 frames in a row with a board, 1.8x blurrier than the median of the frames
  accepted so far. Cameras that report nothing still show this (the edge blur of a board at 0.6 m
  roughly doubles when a webcam's focus slides by a tenth of its range; a hand's stillness varies
  the measure by ~20% frame to frame, so 1.8x over 15 frames is not a bad stretch of holding).

Live, the event is written into the recording the moment it fires (`RecordingWriter.note_event`);
a replay applies recorded events as well as its own watch, so a recording whose control reports
were lost still stops where the live session stopped. Frames from the first soft frame of the run
on are left out of the final solve: they were already soft when they were decided.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibcoach.drivers.base import Frame

FOCUS_CONTROL_KEYS = ("focus_absolute", "lens_position", "focus_position", "visca_focus_position")
FOCUS_EVENT = "focus_drift"  # the kinds of event a recording stores
RELOCK_EVENT = "focus_relocked"  # a resumed capture went on at the recorded lock: accepting again from frame_index
SOFT_RATIO = 1.8  # blur over the accepted frames' median that counts as soft
SOFT_RUN = 15  # soft frames in a row (with a board) before the focus is declared moved
MIN_ACCEPTED_FOR_SOFTNESS = 5  # a median of fewer accepted blurs is too noisy to compare with
CONTROL_TOLERANCE = 0.5  # control units; drivers report integers, so any real move exceeds it


@dataclass(frozen=True, slots=True)
class FocusEvent:
    """A drift: acceptance stopped after `frame_index`, frames from `first_bad_index` on are left out.
    A relock (kind RELOCK_EVENT): a resumed capture accepts again from `frame_index` on."""

    frame_index: int  # drift: the frame at which it was noticed (decided before the stop); relock: the first frame
    first_bad_index: int  # drift: the first frame already affected (the start of a soft run), <= frame_index
    detail: str  # what moved, in words
    kind: str = FOCUS_EVENT

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "frame_index": self.frame_index, "first_bad_index": self.first_bad_index,
                "detail": self.detail}

    @staticmethod
    def from_dict(entry: Mapping[str, Any]) -> FocusEvent:
        index = int(entry["frame_index"])
        return FocusEvent(index, int(entry.get("first_bad_index", index)), str(entry.get("detail", "focus drifted")),
                          str(entry["kind"]))

    def due(self, frame_index: int) -> bool:
        """Whether the event applies before `frame_index` is decided."""
        return self.frame_index < frame_index if self.kind == FOCUS_EVENT else self.frame_index <= frame_index


def focus_events(entries: Iterable[Mapping[str, Any]]) -> tuple[FocusEvent, ...]:
    """The focus events (drifts, relocks) among a recording's stored events, in recorded order."""
    return tuple(FocusEvent.from_dict(e) for e in entries if isinstance(e, Mapping)
                 and e.get("kind") in (FOCUS_EVENT, RELOCK_EVENT) and isinstance(e.get("frame_index"), int))


def focus_controls(controls: Mapping[str, Any]) -> dict[str, float]:
    """The focus-related controls among `controls`, as floats."""
    return {k: float(v) for k, v in controls.items() if k in FOCUS_CONTROL_KEYS}


def lock_mismatch(recorded: Mapping[str, Any], now: Mapping[str, Any]) -> str | None:
    """Why a resumed capture cannot go on at the new lock, or None when both locks agree."""
    old, new = focus_controls(recorded), focus_controls(now)
    moved = [f"{k} {old[k]:g} then, {new[k]:g} now" for k in old.keys() & new.keys()
             if abs(old[k] - new[k]) > CONTROL_TOLERANCE]
    return "; ".join(sorted(moved)) or None


class FocusWatch:
    """Stops acceptance when the lens moves: a focus control reads back different, or frames go soft.

    Args:
        locked: the controls read back after locking (only the focus-related ones are watched).
        from_index: frames before it are not watched (a resumed capture's recorded part, already judged).
    """

    def __init__(self, locked: Mapping[str, Any] | None = None, *, from_index: int = 0) -> None:
        self.locked = focus_controls(locked or {})
        self.from_index = from_index
        self.event: FocusEvent | None = None
        self._soft_run = 0
        self._soft_since: int | None = None

    def check(self, frame: Frame, blur_px: float | None, accepted_blurs: list[float]) -> FocusEvent | None:
        """Look at one decided frame; returns the event when this frame reveals the drift."""
        if self.event is not None or frame.index < self.from_index:
            return None
        for key, value in self.locked.items():
            now = frame.controls.get(key)
            if now is not None and abs(float(now) - value) > CONTROL_TOLERANCE:
                self.event = FocusEvent(frame.index, frame.index,
                                        f"{key} moved from {value:g} to {float(now):g} at frame {frame.index}")
                return self.event
        if blur_px is None or not np.isfinite(blur_px) or len(accepted_blurs) < MIN_ACCEPTED_FOR_SOFTNESS:
            return None
        median = float(np.median(accepted_blurs))
        if blur_px > SOFT_RATIO * median:
            self._soft_run += 1
            self._soft_since = frame.index if self._soft_since is None else self._soft_since
        else:
            self._soft_run, self._soft_since = 0, None
        if self._soft_run >= SOFT_RUN:
            self.event = FocusEvent(frame.index, int(self._soft_since if self._soft_since is not None else frame.index),
                                    f"the last {SOFT_RUN} frames with a board are {blur_px / median:.1f}x blurrier than "
                                    f"the accepted ones (frame {frame.index}): focus drifted")
            return self.event
        return None
