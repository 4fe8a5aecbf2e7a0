"""Rerun logging in a child process, for replays that save session.rrd and show nothing live.

A replay's Rerun log costs ~0.4 s to import rerun and ~1 ms of Python per frame. On a thread of
the replay's own process that Python takes turns at the GIL with the replay's and the final
solve's, and so adds its whole time to the command (`BackgroundViewer`, app/viewer_thread.py,
measured 0.3-0.4 s on a 784-frame 720p folder). A child process has a GIL of its own: it buffers
what it is sent until `start()` (the reading is done), then imports rerun and writes session.rrd
on the other core while the final solve and the outputs are computed here.

What is sent: each frame's outcome with its preview JPEG and the frame without its pixels,
encoded and pickled on a sending thread here (off the replay's path) and written to the child's
stdin in order (app/viewer_child.py reads it). The child runs in a session of its own, so the
Ctrl-C meant for the replay does not cut the log short; `close()` waits for it and raises,
naming the child's last words, if it failed. Where no child can be started at all,
`commands.open_replay_viewer` falls back on the logging thread (app/viewer_thread.py).
"""

from __future__ import annotations

import copy
import pickle
import queue
import subprocess
import sys
import threading
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from calibcoach.app.preview import frame_for_log
from calibcoach.app.viewer_child import START
from calibcoach.drivers.errors import CalibcoachError

if TYPE_CHECKING:  # rerun is imported in the child only
    from calibcoach.app.session import FrameOutcome, SessionResult
    from calibcoach.drivers.base import Frame


_MAX_PENDING = 32  # frames waiting to be encoded and sent (~30 MB at 720p) before the replay waits


class LoggerError(CalibcoachError):
    """The child process that writes session.rrd failed."""


class ProcessViewer:
    """The `Viewer` calls a replay makes (log_frame, start, log_result, close), run in a child process."""

    url: str | None = None  # saving only: nothing to open
    notice: str | None = None

    def __init__(self, out_dir: Path) -> None:
        self._child = subprocess.Popen(
            [sys.executable, "-m", "calibcoach.app.viewer_child", str(out_dir)],
            stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True,
        )
        self._said: list[bytes] = []  # the child's stderr, read on a thread so that it never blocks writing it
        self._reader = threading.Thread(target=lambda: self._said.extend(self._child.stderr), daemon=True)  # type: ignore[arg-type]
        self._reader.start()
        self._closed = False
        self._error: Exception | None = None  # what the sending thread hit
        # Frames are encoded, pickled and written on a thread of their own, off the replay's path;
        # the queue bounds the frames held meanwhile (~30 MB at 720p).
        self._outbox: queue.Queue[tuple[FrameOutcome, Frame] | bytes | None] = queue.Queue(maxsize=_MAX_PENDING)
        self._writer = threading.Thread(target=self._write_all, name="rerun-send", daemon=True)
        self._writer.start()

    def log_frame(self, outcome: FrameOutcome, frame: Frame) -> None:
        if outcome.decision.accepted:  # the map is the session's live one: send it as it is now
            outcome = replace(outcome, coverage=copy.deepcopy(outcome.coverage))
        self._put((outcome, frame))

    def _put(self, item: tuple[FrameOutcome, Frame] | bytes | None) -> None:
        if self._closed:
            raise RuntimeError("the viewer is closed")
        self._outbox.put(item)

    def _write_all(self) -> None:
        while (item := self._outbox.get()) is not None:
            if self._error is not None:
                continue  # keep taking, so the replay never blocks on a full queue; close() reports it
            try:
                if isinstance(item, bytes):
                    self._write(item)
                else:
                    outcome, frame = item
                    pixelless, jpeg = frame_for_log(frame)
                    self._write(_message(("log_frame", (outcome, pixelless), {"jpeg": jpeg})))
            except Exception as exc:  # noqa: BLE001 - e.g. an outcome that does not pickle: handed to close()
                self._error = exc

    def start(self) -> None:
        """The reading is done: the child imports rerun and writes what it holds."""
        self._put(START)

    def log_result(self, result: SessionResult, out_dir: Path) -> None:
        self._put(_message(("log_result", (result, out_dir), {})))

    def _write(self, data: bytes) -> None:
        try:
            self._child.stdin.write(data)  # type: ignore[union-attr]
            self._child.stdin.flush()  # type: ignore[union-attr]
        except OSError:  # BrokenPipeError among them
            pass  # the child has died: close() says why

    def close(self) -> None:
        """Wait until session.rrd is complete; raise LoggerError, with the child's reason, if it failed."""
        if self._closed:
            return
        self._outbox.put(None)
        self._closed = True
        self._writer.join()
        try:
            self._child.stdin.close()  # type: ignore[union-attr]
        except OSError:
            pass
        code = self._child.wait()
        self._reader.join(timeout=5.0)
        self._child.stderr.close()  # type: ignore[union-attr]
        if self._error is not None:
            raise LoggerError(f"writing session.rrd failed ({type(self._error).__name__}: {self._error}); "
                              "the calibration files are unaffected") from self._error
        if code != 0:
            said = b"".join(self._said).decode(errors="replace").strip().splitlines()
            raise LoggerError(f"writing session.rrd failed ({said[-1] if said else f'exit code {code}'}); "
                              "the calibration files are unaffected")

    def __enter__(self) -> ProcessViewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _message(item: tuple[str, tuple, dict]) -> bytes:
    """One message for app/viewer_child.py: its length, then the pickled (method, args, kwargs)."""
    blob = pickle.dumps(item, protocol=pickle.HIGHEST_PROTOCOL)
    return len(blob).to_bytes(4, "big") + blob
