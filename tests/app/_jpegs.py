"""JPEGs as webcams send them, for the MJPG tests (tests/drivers/test_avi_mjpg.py, test_recording.py)."""

from __future__ import annotations


def without_huffman_tables(jpeg: bytes) -> bytes:
    """The JPEG without its DHT segments, as webcams' MJPG (AVI1) sends it: decoders then use the
    standard tables, which are the ones OpenCV's encoder writes."""
    kept, at = bytearray(jpeg[:2]), 2
    while jpeg[at + 1] != 0xDA:  # segments up to the start of scan
        length = int.from_bytes(jpeg[at + 2:at + 4], "big")
        if jpeg[at + 1] != 0xC4:
            kept += jpeg[at:at + 2 + length]
        at += 2 + length
    return bytes(kept + jpeg[at:])
