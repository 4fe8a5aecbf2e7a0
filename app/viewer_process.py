"""Rerun logging in a forked child process, for replays that save session.rrd and show nothing live.

A replay's Rerun log costs ~0.25 s to import rerun and ~1 ms of Python per logged frame. On a
thread of the replay's own process that Python takes turns at the GIL with the replay's and the
final solve's, and so adds its whole time to the command (`BackgroundViewer`,
app/viewer_thread.py, measured 0.3-0.4 s on a 784-frame 720p folder). A child process has a GIL
of its own.

While the source is read, each frame's preview JPEG is encoded on a thread here (OpenCV releases
the GIL) and kept with the outcome and the frame without its pixels (~15 KB a 720p frame). When
the reading is done (`start()`), the process forks: the child is born holding those frames and
every module the replay imported (NumPy, OpenCV, calibcoach), so it imports only rerun and writes
session.rrd (app/viewer_child.py; the frames as columns, app/viewer_columns.py) on the other core
while the final solve and the outputs are computed here. Against a child started with the replay
and sent every frame pickled through a pipe, that is ~0.3 s less CPU on a 720p replay (its own
interpreter and imports, pickling both ways), at a time when both cores are busy. What comes later (the result) goes down a pipe.

The child runs in a session of its own, so the Ctrl-C meant for the replay does not cut the log
short; its stderr comes back on a pipe, and `close()` waits for it and raises, naming the child's
last words, if it failed. None of this module's threads runs across the fork (the encoding
thread has finished; the stderr reader starts after), and OpenCV's pool is down to one thread
since the scan's own fork (app/scan_process.py), so the child never waits on a lock or a pool
thread it was not born with. Where fork is not available (`fork_available`), `commands.open_replay_viewer`
falls back on the logging thread (app/viewer_thread.py).
"""

from __future__ import annotations

import os
import queue
import signal
import sys
import threading
import time
import traceback
from pathlib import Path
from typing import TYPE_CHECKING

from calibcoach.app.preview import frame_for_log, outcome_for_log
from calibcoach.app.viewer_child import log_session, message
from calibcoach.drivers.errors import CalibcoachError

if TYPE_CHECKING:  # rerun is imported in the child only
    from calibcoach.app.session import FrameOutcome, SessionResult
    from calibcoach.drivers.base import Frame


_MAX_PENDING = 32  # frames waiting to be encoded (~30 MB at 720p) before the replay waits


class LoggerError(CalibcoachError):
    """The child process that writes session.rrd failed."""


class ProcessViewer:
    """The `Viewer` calls a replay makes (log_frame, start, log_result, close), logged by a forked child."""

    url: str | None = None  # saving only: nothing to open
    notice: str | None = None

    def __init__(self, out_dir: Path) -> None:
        self._out_dir = Path(out_dir)
        # what the child is born with: (outcome, frame without pixels, preview JPEG, when the replay judged it)
        self._frames: list[tuple[FrameOutcome, Frame, bytes | None, float]] = []
        self._error: Exception | None = None  # what the encoding thread hit
        self._closed = False
        self._child: int | None = None  # its pid, once forked
        self._to_child: int | None = None  # the pipe's writing end
        self._said: list[bytes] = []  # the child's stderr, read on a thread so that it never blocks writing it
        self._reader: threading.Thread | None = None
        # Previews are encoded on a thread of their own, off the replay's path; the queue bounds the
        # full frames held meanwhile (~30 MB at 720p).
        self._outbox: queue.Queue[tuple[FrameOutcome, Frame, float] | None] = queue.Queue(maxsize=_MAX_PENDING)
        self._encoder = threading.Thread(target=self._encode_all, name="rerun-previews", daemon=True)
        self._encoder.start()

    def log_frame(self, outcome: FrameOutcome, frame: Frame) -> None:
        if self._child is not None or self._closed:
            raise RuntimeError("log_frame after start(): the child writing session.rrd was born with the frames before it")
        self._outbox.put((outcome_for_log(outcome), frame, time.perf_counter()))  # its time: the processed frame rate

    def _encode_all(self) -> None:
        while (item := self._outbox.get()) is not None:
            if self._error is not None:
                continue  # keep taking, so the replay never blocks on a full queue; close() reports it
            try:
                outcome, frame, judged_s = item
                pixelless, jpeg = frame_for_log(frame)
                self._frames.append((outcome, pixelless, jpeg, judged_s))
            except Exception as exc:  # noqa: BLE001 - handed to close()
                self._error = exc

    def start(self) -> None:
        """The reading is done: fork the child that writes session.rrd (idempotent)."""
        if self._child is not None or self._closed:
            return
        self._outbox.put(None)
        self._encoder.join()
        messages_in, to_child = os.pipe()
        said_in, said_out = os.pipe()
        sys.stdout.flush()
        sys.stderr.flush()
        # Ctrl-C stays pending until the child has left the replay's session (and is ignored there)
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            pid = os.fork()
        except OSError as exc:  # out of memory or processes: the calibration goes on without session.rrd
            signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
            for fd in (messages_in, to_child, said_in, said_out):
                os.close(fd)
            self._error = self._error or exc
            self._child, self._frames = -1, []
            return
        if pid == 0:  # the child: never returns
            os.close(to_child)
            os.close(said_in)
            _child_main(self._out_dir, self._frames, messages_in, said_out, blocked)
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
        os.close(messages_in)
        os.close(said_out)
        self._child, self._to_child = pid, to_child
        self._frames = []  # the child has them
        self._reader = threading.Thread(target=self._read_said, args=(said_in,), daemon=True)
        self._reader.start()

    def _read_said(self, fd: int) -> None:
        with os.fdopen(fd, "rb") as said:
            self._said.extend(said)

    def log_result(self, result: SessionResult, out_dir: Path) -> None:
        self._send(message("log_result", result, out_dir))

    def _send(self, data: bytes) -> None:
        if self._closed:
            raise RuntimeError("the viewer is closed")
        self.start()
        if self._to_child is None:
            return  # no child could be started: close() says so
        view = memoryview(data)
        try:
            while view:
                view = view[os.write(self._to_child, view):]
        except OSError:  # BrokenPipeError among them
            pass  # the child has died: close() says why

    def close(self) -> None:
        """Wait until session.rrd is complete; raise LoggerError, with the child's reason, if it failed."""
        if self._closed:
            return
        self.start()
        self._closed = True
        code = 0
        if self._to_child is not None:
            os.close(self._to_child)
            _pid, status = os.waitpid(self._child, 0)  # type: ignore[arg-type]
            code = os.waitstatus_to_exitcode(status)
            self._reader.join(timeout=5.0)  # type: ignore[union-attr]
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


def _child_main(out_dir: Path, frames: list, messages_fd: int, said_fd: int, signal_mask: set) -> None:
    """The forked child: its own session (Ctrl-C is the replay's to handle), stderr to the parent, log, exit."""
    code = 1
    try:
        os.setsid()
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.pthread_sigmask(signal.SIG_SETMASK, signal_mask)
        os.dup2(said_fd, 2)
        os.close(said_fd)
        quiet = os.open(os.devnull, os.O_RDWR)  # nothing of the child's on the replay's stdout, nothing read from its stdin
        os.dup2(quiet, 0)
        os.dup2(quiet, 1)
        os.close(quiet)
        with os.fdopen(messages_fd, "rb") as messages:
            log_session(out_dir, frames, messages)
        code = 0
    except BaseException:  # noqa: BLE001 - every failure ends here, told on stderr
        traceback.print_exc()
    finally:
        try:
            sys.stderr.flush()
        finally:
            # session.rrd is closed: leave without the interpreter's teardown (or the parent's atexit handlers)
            os._exit(code)
