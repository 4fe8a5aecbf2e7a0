"""The child process that writes a replay's session.rrd (app/viewer_process.py sends it the work).

Its stdin carries messages in order, each a 4-byte big-endian length and a pickled
(method, args, kwargs) of `Viewer`; an empty message (`START`) says the reading is done. Until
then messages are only held, not even unpickled: unpickling imports calibcoach's modules and
rerun, CPU the replay needs. End of input ends the log. Only the standard library is imported
up front.
"""

from __future__ import annotations

import os
import pickle
import signal
import sys
from pathlib import Path

START = (0).to_bytes(4, "big")


def _open(out_dir: Path, held: list[bytes]):
    from calibcoach.app.viewer import Viewer  # rerun: ~0.4 s, now that the replay has read its source

    viewer = Viewer.open("none", out_dir=out_dir)
    for blob in held:
        _apply(viewer, blob)
    held.clear()
    return viewer


def _apply(viewer, blob: bytes) -> None:
    method, args, kwargs = pickle.loads(blob)
    getattr(viewer, method)(*args, **kwargs)


def main(out_dir: Path) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the replay handles Ctrl-C and then closes this log
    stream = sys.stdin.buffer
    held: list[bytes] = []
    viewer = None
    while len(head := stream.read(4)) == 4:
        size = int.from_bytes(head, "big")
        if size == 0:
            viewer = viewer or _open(out_dir, held)
            continue
        blob = stream.read(size)
        if len(blob) < size:
            break  # the replay died mid-message: log what came whole
        if viewer is None:
            held.append(blob)
        else:
            _apply(viewer, blob)
    viewer = viewer or _open(out_dir, held)
    viewer.close()


if __name__ == "__main__":
    main(Path(sys.argv[1]))
    # session.rrd is flushed and closed: leave without tearing down rerun and NumPy (~0.09 s the
    # replay would wait for before it can exit itself)
    sys.stderr.flush()
    os._exit(0)
