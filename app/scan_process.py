"""The replay's scan in a process of its own: decoding, detection and tracking beside the session.

A replay runs two kinds of work: the scan (decode every frame, thumbnail it, detect or track the
board: app/scan.py) and the session's judgement of what the scan saw (app/session.py). Both are
Python driving many short OpenCV and NumPy calls, and in one process they share one GIL: every
OpenCV call releases it, and getting it back waits for whichever other thread is running Python
at that moment. On a 784-frame 720p folder the session's thread used 2.1 s of CPU but took 3.4 s
beside the scan's threads, and the scan in its own process brought the whole read from 4.3 s to
3.5 s with the same decisions (OpenCV 5.1, 2 cores).

So footage is scanned in a forked child process. The child runs the very generator a replay runs
in process (`detected_frames`); each frame's pixels (of a colour frame the session only tracks
or skips, its grey; of one it judges, its colour and the grey the scan made of it; of an MJPG
frame, its grey, and the JPEG it came from with a frame the session judges) go through a ring of
shared-memory slots (a semaphore counts the free ones, so the child never runs more than the ring
ahead) and the rest of what it saw through a pipe, in order. The parent copies the pixels out
(0.1 ms at 720p) and frees the slot, so frames it keeps (a hold waiting for its judgement) never
pin the ring.

State the child learns that the parent needs (the print's settled variant, the scan's counters,
frames the source could not decode) is sent with every frame and handed to `apply_state` before
the frame is yielded, so the parent sees it exactly when an in-process scan would have shown it.

Closing the iterator (the stop rule, Ctrl-C, an error in the session) ends the child. The child
ignores SIGINT, so Ctrl-C reaches only the parent, which stops reading and keeps what it accepted.
The ring is an anonymous shared mapping, not a named POSIX segment: the forked child inherits it,
nothing is left in /dev/shm when either process is killed outright (a named segment outlived a
SIGKILLed bench run), and a container's small /dev/shm (often 64 MB, where a write beyond a full
tmpfs kills with SIGBUS) does not limit it. Where `fork` is not available (`fork_available`), the
caller scans in process, with the same decisions.
"""

from __future__ import annotations

import mmap
import multiprocessing
import os
import signal
from collections.abc import Callable, Iterator
from dataclasses import replace
from types import MappingProxyType
from typing import Any

import cv2
import numpy as np

from calibcoach.app.scan import Seen
from calibcoach.drivers.base import Frame, frames_ahead

_POLL_S = 0.5  # how often a waiting side checks that the other is still there


def fork_available() -> bool:
    return "fork" in multiprocessing.get_all_start_methods()


class ChildScan:
    """The `Seen` frames of `make_seen()`, produced in a child process forked when this is made.

    Iterate it once; `close()` (or leaving `with`) ends the child (if still running) and frees the
    ring, whether or not the frames were read (a caller that fails before reading must still close it).

    Args:
        make_seen: called in the child; its frames must hold images of at most `frame_bytes`.
        frame_bytes: the size of the largest frame (a BGR frame at the source's size).
        state: called in the child after each frame; a small picklable value.
        apply_state: called in the parent with that value before the frame is yielded, and at the end.

    Iterating raises whatever `make_seen` raised in the child (its own exception where it pickles),
    or RuntimeError when the child died without saying why (killed, out of memory).
    """

    def __init__(self, make_seen: Callable[[], Iterator[Seen]], frame_bytes: int, *,
                 state: Callable[[], Any], apply_state: Callable[[Any], None]) -> None:
        slots = frames_ahead(frame_bytes)
        # a colour frame's slot holds its grey too (the scan converted it already: the session
        # judges by the grey, and converting a 1080p frame again took ~5 ms of the session's thread)
        frame_bytes += frame_bytes // 3
        context = multiprocessing.get_context("fork")
        # OpenCV's own thread pool goes down to one thread here, before the fork: the scan detects on
        # threads of its own beside its decoders, so OpenCV's threads inside each call would only
        # oversubscribe the cores (corners are the same either way), and a forked child must never
        # reconfigure a pool whose threads stayed in the parent (it hangs in pthread_cond_destroy; seen
        # when the bench's process had detected with two threads before). The session asks for one
        # thread anyway (app/session.py).
        cv2.setNumThreads(1)
        self._apply_state = apply_state
        self._memory = mmap.mmap(-1, slots * frame_bytes)  # anonymous and MAP_SHARED: the child's writes are seen here
        self._ring: np.ndarray | None = np.frombuffer(self._memory, np.uint8).reshape(slots, frame_bytes)
        self._free = context.Semaphore(slots)
        self._receiving, sending = context.Pipe(duplex=False)
        self._child = context.Process(target=_produce, args=(make_seen, state, sending, self._free, self._ring, os.getpid()),
                                      name="calibcoach-scan", daemon=True)
        self._child.start()
        sending.close()  # the child holds the sending end: the parent sees EOF when it exits
        self._closed = False

    def __iter__(self) -> Iterator[Seen]:
        while not self._closed:
            try:
                message = self._receiving.recv()
            except EOFError:
                self._child.join(timeout=5.0)
                raise RuntimeError(f"the process scanning the frames ended without finishing (exit code {self._child.exitcode}: "
                                   "killed, out of memory or crashed in OpenCV); run the command again") from None
            kind = message[0]
            if kind == "frame":
                _kind, slot, shape, has_grey, (index, timestamp_ns, name, controls, encoded), seen, child_state = message
                if slot is None:  # skipped in transit: no pixels (the replay only counts it)
                    image, grey = np.zeros(shape, np.uint8), None
                else:
                    size = int(np.prod(shape))
                    image = self._ring[slot, :size].reshape(shape).copy()  # type: ignore[index]
                    grey = self._ring[slot, size:size + size // 3].reshape(shape[:2]).copy() if has_grey else None  # type: ignore[index]
                    self._free.release()
                self._apply_state(child_state)
                frame = Frame(index, timestamp_ns, image, name, MappingProxyType(controls), encoded=encoded)
                if grey is not None:
                    frame.keep_grey(grey)
                yield replace(seen, frame=frame)
            elif kind == "end":
                self._apply_state(message[1])
                return
            else:  # "error"
                self._apply_state(message[2])
                raise message[1]

    def close(self) -> None:
        """End the child if it still runs and free the ring (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self._child.is_alive():
            self._child.terminate()
        self._child.join()
        self._receiving.close()
        self._ring = None  # the array's hold on the mapping goes first, or close() refuses
        self._memory.close()

    def __enter__(self) -> ChildScan:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _pixels_for_the_session(seen: Seen) -> np.ndarray:
    """The pixels the replay needs of a frame it judges or tracks: a tracked frame's in grey only.

    The replay judges a tracked frame by its grey image alone (`CalibrationSession.sharp_edges`);
    it is neither logged nor previewed, so of a colour frame the grey conversion the scan already
    made crosses (a third of the bytes, and no second conversion in the replay). Frames the
    session decides keep their colour (previews, the check image): a BGR frame's pixels, or an
    MJPG frame's JPEG beside its grey (`Frame.encoded`). The decisions are the same: the replay
    would convert those frames to exactly this grey. A frame skipped in transit is only counted:
    none of its pixels cross (`_produce`).
    """
    return seen.frame.image if seen.detected_in_full else seen.frame.grey()


def _produce(make_seen: Callable[[], Iterator[Seen]], state: Callable[[], Any], sending: Any,
             free: Any, ring: np.ndarray, parent_pid: int) -> None:
    """The child: scan, and hand every frame over in order (runs after fork; exits with the parent's pipe)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle: it ends this process
    slots, frame_bytes = ring.shape
    try:
        slot = -1
        for seen in make_seen():
            frame = seen.frame
            if seen.skipped:  # only counted by the replay: its index and time cross, not its pixels
                sending.send(("frame", None, (0, 0), False, (frame.index, frame.timestamp_ns, frame.name, dict(frame.controls), None),
                              replace(seen, frame=None), state()))
                continue
            image = np.ascontiguousarray(_pixels_for_the_session(seen))
            grey = seen.frame.grey_made if image.ndim == 3 else None  # converted here for detection or tracking
            if image.nbytes + (0 if grey is None else grey.nbytes) > frame_bytes:
                raise ValueError(f"frame {seen.frame.index} is {image.shape}, larger than the source's "
                                 f"{frame_bytes * 3 // 4} bytes a frame")
            while not free.acquire(timeout=_POLL_S):
                if os.getppid() != parent_pid:  # the parent died without ending this process
                    return
            slot = (slot + 1) % slots  # the slots are freed in the order they are filled
            ring[slot, : image.nbytes] = image.reshape(-1)
            if grey is not None:
                ring[slot, image.nbytes : image.nbytes + grey.nbytes] = grey.reshape(-1)
            # an MJPG frame's JPEG goes along where the session may show the frame in colour (see above)
            encoded = frame.encoded if seen.detected_in_full else None
            sending.send(("frame", slot, image.shape, grey is not None,
                          (frame.index, frame.timestamp_ns, frame.name, dict(frame.controls), encoded),
                          replace(seen, frame=None), state()))
        sending.send(("end", state()))
    except BaseException as exc:  # noqa: BLE001 - handed to the parent, which raises it
        try:
            sending.send(("error", exc, state()))
        except Exception:  # noqa: BLE001 - the exception does not pickle: its words do
            sending.send(("error", RuntimeError(f"{type(exc).__name__}: {exc}"), state()))
    finally:
        sending.close()
