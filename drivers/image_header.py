"""An image file's pixel size read from its header, without decoding it.

A folder of photos is one camera only if its images share one size; which size is the camera's is
decided by the majority (a stray screenshot or thumbnail sorted first must not disqualify the
rest), so every file's size is wanted before the first frame is decoded. PNG keeps it in IHDR,
JPEG in its SOF segment; other formats return None (the caller decodes them).

The size is the stored one, before any EXIF orientation: calibcoach decodes with
IMREAD_IGNORE_ORIENTATION, as a sensor's pixels do not turn with the phone.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import BinaryIO

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers (baseline, progressive, lossless, ...): C0-CF except DHT (C4), JPG
# (C8) and DAC (CC), which share the range but carry no frame size.
_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
_MAX_SEGMENTS = 64  # a JPEG reaches its SOF within a few segments; a file that does not is not parsed further


def header_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG or JPEG header; None for other formats or a header that does not parse."""
    try:
        with path.open("rb") as f:
            head = f.read(24)
            if head.startswith(_PNG_SIGNATURE) and head[12:16] == b"IHDR":
                width, height = struct.unpack(">II", head[16:24])
                return (int(width), int(height)) if width > 0 and height > 0 else None
            if head.startswith(b"\xff\xd8"):
                f.seek(2)
                return _jpeg_size(f)
    except OSError:
        return None
    return None


def _jpeg_size(f: BinaryIO) -> tuple[int, int] | None:
    """Walk the JPEG's segments from after SOI (each: 0xFF, marker, 2-byte length) to the first SOF,
    seeking over the others (an EXIF segment, thumbnail and all, is skipped unread)."""
    for _ in range(_MAX_SEGMENTS):
        head = f.read(4)
        if len(head) < 4 or head[0] != 0xFF:
            return None
        marker = head[1]
        if marker == 0xFF:  # a fill byte: the marker follows
            f.seek(-3, 1)
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length
            f.seek(-2, 1)
            continue
        (length,) = struct.unpack(">H", head[2:4])
        if marker in _SOF_MARKERS:
            body = f.read(5)
            if len(body) < 5:
                return None
            height, width = struct.unpack(">HH", body[1:5])
            return (int(width), int(height)) if width > 0 and height > 0 else None
        if marker == 0xDA or length < 2:  # start of scan before any SOF, or a broken length
            return None
        f.seek(length - 2, 1)
    return None
