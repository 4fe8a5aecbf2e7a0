"""Rerun logging in a forked child process, for replays that save session.rrd and show nothing live.

A replay's Rerun log costs ~0.45 s of CPU to import rerun and ~1 ms of Python per logged frame.
On a thread of the replay's own process that Python takes turns at the GIL with the replay's and
the final solve's, and so adds its whole time to the command (`BackgroundViewer`,
app/viewer_thread.py, measured 0.3-0.4 s on a 784-frame 720p folder). A child process has a GIL
of its own.

The child is forked when the viewer is made, before the source is read, and imports rerun at once
at the lowest CPU priority (nice 19): a replay keeps both cores busy, but not always -- the session
waits for the scan's frames now and then -- and the import runs in those gaps instead of beside
the final solve, whose threads, the outputs' and this child's rerun import all wanted the two
cores at once (the import was ~0.45 of the ~2 s of CPU the last second of a careful 720p replay
spends). Born from the replay's process, it holds NumPy, OpenCV and calibcoach's modules already.

While the source is read, each frame's preview JPEG is encoded on a thread here (OpenCV releases
the GIL) and kept with the outcome and the frame without its pixels (~15 KB a 720p frame); every
`_BATCH` frames go down the pipe to the child as one message, which it logs as columns
(app/viewer_child.py, app/viewer_columns.py), again in the CPU the read leaves. The pipe is written
without blocking: what it cannot take yet waits here for the next batch, so a starved child never
holds up the replay, and `start()` (the reading is done) sends the rest. What comes later (the
result) follows down the same pipe. The child's priority costs nothing at the end: the replay
waits for it in `close()`, and then it has the cores. Sent only at the end instead, the frames
were logged after the final solve and the outputs (the child had had no CPU beside them) while the
replay waited: 0.2 s of a careful 720p replay's ~4 s.

The child runs in a session of its own, so the Ctrl-C meant for the replay does not cut the log
short; its stderr comes back on a pipe, and `close()` waits for it and raises, naming the child's
last words, if it failed. No thread of this module exists at the fork (the encoding thread starts
after it), and OpenCV's pool is down to one thread since the scan's own fork
(app/scan_process.py), so the child never waits on a lock or a pool thread it was not born with.
A replay killed outright closes the pipe: the child logs the frames it had and closes session.rrd
(writes nothing if none had come).
Where fork is not available (`fork_available`), `commands.open_replay_viewer` falls back on the
logging thread (app/viewer_thread.py).
"""

from __future__ import annotations

import os
import queue
import select
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
_BATCH = 16  # frames a message: ~250 KB at 720p, a pickle and a wake-up of the child per 16 frames


class LoggerError(CalibcoachError):
    """The child process that writes session.rrd failed."""


class ProcessViewer:
    """The `Viewer` calls a replay makes (log_frame, start, log_result, close), logged by a forked child."""

    url: str | None = None  # saving only: nothing to open
    notice: str | None = None

    def __init__(self, out_dir: Path) -> None:
        self._out_dir = Path(out_dir)
        # the batch being filled: (outcome, frame without pixels, preview JPEG, when the replay judged it)
        self._frames: list[tuple[FrameOutcome, Frame, bytes | None, float]] = []
        self._error: Exception | None = None  # what the encoding thread hit, or the fork
        self._closed = False
        self._started = False  # the frames went to the child
        self._child: int | None = None  # its pid (None: no child could be forked)
        self._to_child: int | None = None  # the pipe's writing end
        self._said: list[bytes] = []  # the child's stderr, read on a thread so that it never blocks writing it
        self._reader: threading.Thread | None = None
        self._unsent = bytearray()  # messages of frames the pipe could not take yet (the encoding thread's)
        self._fork_child()  # before any thread of this object exists
        # Previews are encoded on a thread of their own, off the replay's path; the queue bounds the
        # full frames held meanwhile (~30 MB at 720p).
        self._outbox: queue.Queue[tuple[FrameOutcome, Frame, float] | None] = queue.Queue(maxsize=_MAX_PENDING)
        self._encoder = threading.Thread(target=self._encode_all, name="rerun-previews", daemon=True)
        self._encoder.start()

    def _fork_child(self) -> None:
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
            self._error = exc
            return
        if pid == 0:  # the child: never returns
            os.close(to_child)
            os.close(said_in)
            _child_main(self._out_dir, messages_in, said_out, blocked)
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
        os.close(messages_in)
        os.close(said_out)
        self._child, self._to_child = pid, to_child
        os.set_blocking(to_child, False)  # see `_write_some`, `_send`
        self._reader = threading.Thread(target=self._read_said, args=(said_in,), daemon=True)
        self._reader.start()

    def log_frame(self, outcome: FrameOutcome, frame: Frame) -> None:
        if self._started or self._closed:
            raise RuntimeError("log_frame after start(): the frames went to the child writing session.rrd")
        self._outbox.put((outcome_for_log(outcome), frame, time.perf_counter()))  # its time: the processed frame rate

    def _encode_all(self) -> None:
        """The encoding thread: previews, batched into messages, sent as far as the pipe takes them."""
        while (item := self._outbox.get()) is not None:
            if self._error is not None:
                continue  # keep taking, so the replay never blocks on a full queue; close() reports it
            try:
                outcome, frame, judged_s = item
                pixelless, jpeg = frame_for_log(frame)
                self._frames.append((outcome, pixelless, jpeg, judged_s))
                if len(self._frames) >= _BATCH:
                    self._unsent += message("log_frames", self._frames)
                    self._frames = []
                if self._unsent and self._to_child is not None:
                    self._unsent = self._unsent[_write_some(self._to_child, self._unsent):]
            except Exception as exc:  # noqa: BLE001 - handed to close()
                self._error = exc

    def start(self) -> None:
        """The reading is done: send the child the frames it has not had yet (idempotent)."""
        if self._started or self._closed:
            return
        self._started = True
        self._outbox.put(None)
        self._encoder.join()
        rest, self._unsent = bytes(self._unsent) + message("log_frames", self._frames), bytearray()
        self._frames = []
        self._send(rest)

    def _read_said(self, fd: int) -> None:
        with os.fdopen(fd, "rb") as said:
            self._said.extend(said)

    def log_result(self, result: SessionResult, out_dir: Path) -> None:
        self.start()
        self._send(message("log_result", result, out_dir))

    def _send(self, data: bytes) -> None:
        if self._closed:
            raise RuntimeError("the viewer is closed")
        if self._to_child is None:
            return  # no child could be started: close() says so
        view = memoryview(data)
        while view:
            view = view[_write_some(self._to_child, view):]
            if view:
                select.select([], [self._to_child], [])  # full: wait until the child has read some

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


def _write_some(fd: int, data: bytes | bytearray | memoryview) -> int:
    """Write what the non-blocking pipe `fd` takes of `data` now; how many bytes that was (0 when
    full; all of them when the reader has gone)."""
    try:
        return os.write(fd, data)
    except BlockingIOError:
        return 0
    except BrokenPipeError:
        return len(data)  # the child has died: nothing more to send, and close() says why


def _child_main(out_dir: Path, messages_fd: int, said_fd: int, signal_mask: set) -> None:
    """The forked child: its own session (Ctrl-C is the replay's to handle), stderr to the parent, the
    lowest CPU priority, rerun imported at once, then the log; exits."""
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
        _lowest_priority()
        with os.fdopen(messages_fd, "rb") as messages:
            log_session(out_dir, messages)
        code = 0
    except BaseException:  # noqa: BLE001 - every failure ends here, told on stderr
        traceback.print_exc()
    finally:
        try:
            sys.stderr.flush()
        finally:
            # session.rrd is closed: leave without the interpreter's teardown (or the parent's atexit handlers)
            os._exit(code)


def _lowest_priority() -> None:
    """nice 19 for this process and, where the kernel groups each session for scheduling
    (autogroup), for the session `setsid` just made: across sessions each group gets its fair share
    whatever its processes' nice, so a nice 19 child in a group of its own would still take half
    the CPU from the replay's group while both want it."""
    os.nice(19)
    try:
        with open("/proc/self/autogroup", "w") as group:  # absent without autogroup: nice alone decides
            group.write("19")
    except OSError:
        pass
