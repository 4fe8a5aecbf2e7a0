"""Rerun logging on a thread of its own, for replays that save session.rrd and show nothing live.

Importing rerun costs ~0.4 s of Python and building its messages ~1 ms per frame; on the replay's
thread both add to every frame's time, and even on a thread of their own they hold the GIL the
replay's thread needs. So the logging thread first waits: until the reading is done (`start()`,
then it imports and logs beside the final solve, still taking turns at the GIL with it) or until
`_START_PENDING` frames wait. Meanwhile each frame waits as its preview JPEG (encoded on the
caller's thread, which OpenCV releases the GIL for) beside a copy of the frame without its
pixels, ~50 KB instead of 1-6 MB. One queue keeps the order; `close()` waits until everything is
written and re-raises what went wrong.

A replay's CLI logs in the child process of app/viewer_process.py instead, which has a GIL of its
own; this thread is the fallback where no child can be started. Live sessions keep the direct
`Viewer`: there the preview must not lag behind the camera.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from calibcoach.app.preview import frame_for_log, outcome_for_log

if TYPE_CHECKING:  # the viewer (and rerun) is imported on the logging thread, never here
    from calibcoach.app.session import FrameOutcome, SessionResult
    from calibcoach.app.viewer import Viewer
    from calibcoach.drivers.base import Frame

_START_PENDING = 1000  # frames waiting (~50 MB of previews) before the logger starts without being told


class BackgroundViewer:
    """The `Viewer` calls a replay makes (log_frame, log_result, close), run on a logging thread."""

    url: str | None = None  # saving only: nothing to open
    notice: str | None = None

    def __init__(self, open_viewer: Callable[[], Viewer]) -> None:
        self._queue: queue.Queue[tuple[str, tuple, dict] | None] = queue.Queue()
        self._go = threading.Event()
        self._error: BaseException | None = None
        self._closed = False
        self._thread = threading.Thread(target=self._run, args=(open_viewer,), name="rerun-log", daemon=True)
        self._thread.start()

    def start(self) -> None:
        """Begin logging now (the replay has read its source): import rerun and catch up."""
        self._go.set()

    def _run(self, open_viewer: Callable[[], Viewer]) -> None:
        viewer = None
        try:
            self._go.wait()
            viewer = open_viewer()
            while (item := self._queue.get()) is not None:
                method, args, kwargs = item
                getattr(viewer, method)(*args, **kwargs)
        except BaseException as exc:  # noqa: BLE001 - handed to close(), which re-raises it
            self._error = exc
            while self._queue.get() is not None:  # keep taking, so the replay never blocks on a dead logger
                pass
        finally:
            if viewer is not None:
                viewer.close()

    def log_frame(self, outcome: FrameOutcome, frame: Frame) -> None:
        outcome = outcome_for_log(outcome)
        pixelless, jpeg = frame_for_log(frame)
        self._put(("log_frame", (outcome, pixelless), {"jpeg": jpeg}))

    def log_result(self, result: SessionResult, out_dir: Path) -> None:
        self._put(("log_result", (result, out_dir), {}))

    def _put(self, item: tuple[str, tuple, dict]) -> None:
        if self._closed:
            raise RuntimeError("the viewer is closed")
        self._queue.put(item)
        if self._queue.qsize() >= _START_PENDING:
            self._go.set()

    def close(self) -> None:
        """Wait until everything is logged and session.rrd is complete; raise what the logger hit."""
        if self._closed:
            return
        self._closed = True
        self._go.set()
        self._queue.put(None)
        self._thread.join()
        if self._error is not None:
            raise self._error

    def __enter__(self) -> BackgroundViewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
