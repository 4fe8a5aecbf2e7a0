"""Rerun logging on a thread of its own, for replays that save session.rrd and show nothing live.

Importing rerun costs ~0.8 s and building its messages ~3 ms of Python per frame; on the replay's
thread both add to every frame's time. Here they run on a logging thread that works while the
replay thread waits for detections, so a replay costs little more than its detection. One queue
keeps the order; `close()` waits until everything is written and re-raises what went wrong.
Live sessions keep the direct `Viewer`: there the preview must not lag behind the camera.
"""

from __future__ import annotations

import copy
import queue
import threading
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the viewer (and rerun) is imported on the logging thread, never here
    from calibcoach.app.session import FrameOutcome, SessionResult
    from calibcoach.app.viewer import Viewer
    from calibcoach.drivers.base import Frame

_MAX_PENDING = 32  # frames waiting to be logged (~30 MB at 720p) before the replay waits for the logger


class BackgroundViewer:
    """The `Viewer` calls a replay makes (log_frame, log_result, close), run on a logging thread."""

    url: str | None = None  # saving only: nothing to open
    notice: str | None = None

    def __init__(self, open_viewer: Callable[[], Viewer]) -> None:
        self._queue: queue.Queue[tuple[str, tuple] | None] = queue.Queue(maxsize=_MAX_PENDING)
        self._error: BaseException | None = None
        self._closed = False
        self._thread = threading.Thread(target=self._run, args=(open_viewer,), name="rerun-log", daemon=True)
        self._thread.start()

    def _run(self, open_viewer: Callable[[], Viewer]) -> None:
        viewer = None
        try:
            viewer = open_viewer()
            while (item := self._queue.get()) is not None:
                method, args = item
                getattr(viewer, method)(*args)
        except BaseException as exc:  # noqa: BLE001 - handed to close(), which re-raises it
            self._error = exc
            while self._queue.get() is not None:  # keep taking, so the replay never blocks on a dead logger
                pass
        finally:
            if viewer is not None:
                viewer.close()

    def log_frame(self, outcome: FrameOutcome, frame: Frame) -> None:
        if outcome.decision.accepted:  # the map is the session's live one: log it as it is now
            outcome = replace(outcome, coverage=copy.deepcopy(outcome.coverage))
        self._put(("log_frame", (outcome, frame)))

    def log_result(self, result: SessionResult, out_dir: Path) -> None:
        self._put(("log_result", (result, out_dir)))

    def _put(self, item: tuple[str, tuple]) -> None:
        if self._closed:
            raise RuntimeError("the viewer is closed")
        self._queue.put(item)

    def close(self) -> None:
        """Wait until everything is logged and session.rrd is complete; raise what the logger hit."""
        if self._closed:
            return
        self._closed = True
        self._queue.put(None)
        self._thread.join()
        if self._error is not None:
            raise self._error

    def __enter__(self) -> BackgroundViewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
