"""What the forked child of app/viewer_process.py runs: session.rrd written from the messages on its pipe.

The child is forked as the replay starts, so NumPy, OpenCV and calibcoach's modules are in its
memory already; it imports rerun at once (while the replay reads), then waits. Every message is a
4-byte big-endian length and a pickled (method, args, kwargs): "log_frames" with a batch of the
frames the replay judged (each outcome, its frame without pixels, its preview JPEG, when it was
judged), logged as columns, as they come, then calls of `Viewer` (the final result); end of input
ends the log.
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import BinaryIO


def log_session(out_dir: Path, messages: BinaryIO) -> None:
    """Write out_dir/session.rrd from `messages` (see the module docstring); nothing when the pipe
    closes before the first message (the replay was killed outright)."""
    from calibcoach.app.viewer import Viewer  # rerun: ~0.45 s of CPU, while the replay reads
    from calibcoach.app.viewer_columns import log_frames

    call = _read_message(messages)
    if call is None:
        return
    viewer = Viewer.open("none", out_dir=out_dir)
    try:
        while call is not None:
            method, args, kwargs = call
            if method == "log_frames":  # a batch of the frames the replay judged, as columns
                log_frames(viewer, *args, **kwargs)
            else:
                getattr(viewer, method)(*args, **kwargs)
            call = _read_message(messages)
    finally:
        viewer.close()


def _read_message(messages: BinaryIO) -> tuple[str, tuple, dict] | None:
    """The next (method, args, kwargs), or None at the end of input (or a message cut short: the replay died mid-message)."""
    head = messages.read(4)
    if len(head) < 4:
        return None
    size = int.from_bytes(head, "big")
    blob = messages.read(size)
    if len(blob) < size:
        return None
    return pickle.loads(blob)


def message(method: str, *args: object, **kwargs: object) -> bytes:
    """One message for `log_session`: its length, then the pickled (method, args, kwargs)."""
    blob = pickle.dumps((method, args, kwargs), protocol=pickle.HIGHEST_PROTOCOL)
    return len(blob).to_bytes(4, "big") + blob
