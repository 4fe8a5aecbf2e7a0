"""What the forked child of app/viewer_process.py runs: session.rrd written from the frames it was born with.

The child starts once the replay has read its source, as a fork of the replay's process: the
frames to log (each outcome, its frame without pixels, its preview JPEG) are already in its
memory, and so are NumPy, OpenCV and calibcoach's modules; only rerun is left to import. What
comes after the fork (the final result) arrives on a pipe, each message a 4-byte big-endian length
and a pickled (method, args, kwargs) of `Viewer`; end of input ends the log.
"""

from __future__ import annotations

import pickle
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

if TYPE_CHECKING:
    from calibcoach.app.session import FrameOutcome
    from calibcoach.drivers.base import Frame


def log_session(out_dir: Path, frames: Sequence[tuple[FrameOutcome, Frame, bytes | None, float]], messages: BinaryIO) -> None:
    """Write out_dir/session.rrd: `frames` first (outcome, frame, preview JPEG, when it was judged;
    as columns), then each message until the pipe closes."""
    from calibcoach.app.viewer import Viewer  # rerun: ~0.25 s, beside the replay's final solve
    from calibcoach.app.viewer_columns import log_frames

    viewer = Viewer.open("none", out_dir=out_dir)
    try:
        log_frames(viewer, frames)
        while len(head := messages.read(4)) == 4:
            size = int.from_bytes(head, "big")
            blob = messages.read(size)
            if len(blob) < size:
                break  # the replay died mid-message: log what came whole
            method, args, kwargs = pickle.loads(blob)
            getattr(viewer, method)(*args, **kwargs)
    finally:
        viewer.close()


def message(method: str, *args: object, **kwargs: object) -> bytes:
    """One message for `log_session`: its length, then the pickled (method, args, kwargs)."""
    blob = pickle.dumps((method, args, kwargs), protocol=pickle.HIGHEST_PROTOCOL)
    return len(blob).to_bytes(4, "big") + blob
