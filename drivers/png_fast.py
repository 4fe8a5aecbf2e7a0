"""Faster 8-bit grey and RGB PNGs: ISA-L inflates, a small C loop undoes the row filters; and the
recordings' writer (`encode_png`: Sub rows, ISA-L's deflate).

A replay decodes every frame of a folder, and decoding was ~45% of its time: libpng (through
`cv2.imdecode`) takes ~5-7 ms for a 720p grey PNG (OpenCV 5.0-5.1), most of it zlib 1.2's
inflate. ISA-L's inflate (`isal`) does the same in ~1.1-1.6 ms. The row filters are then undone
by `_png_unfilter.c` (built by `pip install`; pyproject ext-modules), one pass over the rows with
the GIL released: 720p grey, ~1.4 ms in all for OpenCV's own files (every row "Sub", undone 16
bytes at a time) instead of 2.7 with NumPy's prefix sums, and 2.8 ms for libpng's adaptive
choice (Average and Paeth rows, as PIL and OpenCV given a compression level write them) instead
of 4.7 by handing the rows back to libpng (libpng itself: ~9 ms). The zlib stream's Adler-32
checksum still guards the pixels; a damaged file fails to inflate and is left to OpenCV to judge.

Where the C loop was not built (no compiler at install), Sub rows, each byte stored as the
difference to the byte one pixel to its left, are undone as a prefix sum along the row by
doubling in whole-array uint8 additions, and rows with the Up, Average or Paeth filters, which
cannot be undone in whole-array steps, are handed back to libpng in "stored" deflate blocks,
which it copies instead of inflating, so it only unfilters.

Anything else -- 16-bit, palette, alpha or transparency, interlaced -- returns None, and the caller
decodes with OpenCV.

`encode_png` writes what this decoder reads fastest: every row Sub-filtered, deflated by ISA-L at
its level 1. A live session's recording writes every processed frame before using it, and OpenCV's
encoder (zlib level 1, Sub rows) took 25.7-47.5 ms a 720p BGR frame of the bench's videos (12.9-24.9
grey, 52.0 at 1080p), more than a 30 fps stream leaves; this one 7.0-11.4 ms (3.1-8.8 grey, 12.8 at
1080p: ISA-L's deflate is most of it), for files 2% larger to 9% smaller, which libpng reads to the
same pixels.
"""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np

try:  # a dependency (pyproject); without it zlib's own inflate is used, no faster than libpng's
    from isal import isal_zlib as _inflater
except ImportError:  # pragma: no cover - isal has wheels for every platform calibcoach runs on
    _inflater = zlib

try:  # built by `pip install` where a C compiler is present (pyproject ext-modules, optional)
    from calibcoach.drivers._png_unfilter import unfilter as _unfilter_in_c
except ImportError:  # pragma: no cover - no compiler at install: NumPy and libpng unfilter instead
    _unfilter_in_c = None

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_GREY, _RGB = 0, 2  # PNG colour types handled here
_NONE, _SUB = 0, 1  # PNG row filters handled here
_BAIL_CHUNKS = {b"tRNS", b"PLTE"}  # transparency or a palette: OpenCV's output differs, let it decode


def decode_png(data: bytes | memoryview) -> np.ndarray | None:
    """(H, W) uint8 grey or (H, W, 3) uint8 BGR, exactly as `cv2.imdecode` gives it; None when not handled here."""
    inflated = _inflated_rows(data)
    if inflated is None:
        return None
    header, raw, rows = inflated
    width, height, _depth, colour = header[:4]
    channels = 1 if colour == _GREY else 3
    if _unfilter_in_c is None:
        return _unfiltered_in_numpy(header, raw, rows)
    # grey, or RGB stored straight into OpenCV's BGR order
    image = np.empty((height, width, channels) if channels == 3 else (height, width), np.uint8)
    try:
        _unfilter_in_c(rows, height, width * channels, channels, image)
    except ValueError:  # an unknown filter byte: a damaged file, for OpenCV to judge
        return None
    return image


def _unfiltered_in_numpy(header: tuple[int, ...], raw: np.ndarray, rows: np.ndarray) -> np.ndarray | None:
    """Without the C unfilter: Sub and None rows by NumPy prefix sums, any other filter by libpng;
    the image as `decode_png` returns it."""
    width, height, _depth, colour = header[:4]
    channels = 1 if colour == _GREY else 3
    filters = rows[:, 0]
    if np.any(filters > _SUB):
        return _unfiltered_by_libpng(header, raw)
    pixels = rows[:, 1:]
    # Sub: each byte adds the reconstructed byte one pixel (`channels` bytes) to its left, mod 256
    image = _row_prefix_sums(pixels.reshape(height, width, channels)).reshape(height, -1)
    unfiltered = filters == _NONE
    if unfiltered.any():
        image[unfiltered] = pixels[unfiltered]
    if channels == 1:
        return image
    # RGB as stored -> BGR as OpenCV gives it: OpenCV's swap takes 0.2 ms at 720p, NumPy's reversed copy 2.6
    return cv2.cvtColor(image.reshape(height, width, 3), cv2.COLOR_RGB2BGR)


def encode_png(image: np.ndarray) -> bytes:
    """An (H, W) uint8 grey or (H, W, 3) uint8 BGR image as PNG bytes (8-bit grey or RGB, every row
    Sub-filtered), which `cv2.imdecode` and `decode_png` give back exactly.

    Raises:
        ValueError: for any other shape or type.
    """
    if image.dtype != np.uint8 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)) or 0 in image.shape:
        raise ValueError(f"encode_png takes (H, W) or (H, W, 3) uint8 images, got {image.shape} {image.dtype}")
    height, width = image.shape[:2]
    channels = 1 if image.ndim == 2 else 3
    # BGR -> the RGB a PNG stores (OpenCV's swap: 0.1 ms at 720p, NumPy's reversed copy ~8)
    pixels = (np.ascontiguousarray(image) if channels == 1 else cv2.cvtColor(image, cv2.COLOR_BGR2RGB)).reshape(height, -1)
    rows = np.empty((height, width * channels + 1), np.uint8)
    rows[:, 0] = _SUB
    rows[:, 1:1 + channels] = pixels[:, :channels]
    np.subtract(pixels[:, channels:], pixels[:, :-channels], out=rows[:, 1 + channels:])  # uint8 wraps: mod 256
    header = struct.pack(">IIBBBBB", width, height, 8, _GREY if channels == 1 else _RGB, 0, 0, 0)
    return PNG_SIGNATURE + _chunk(b"IHDR", header) + _chunk(b"IDAT", _inflater.compress(rows, 1)) + _chunk(b"IEND", b"")


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(body, zlib.crc32(kind)) & 0xFFFFFFFF)


def row_filters(data: bytes | memoryview) -> np.ndarray | None:
    """(H,) uint8 each row's PNG filter type (0 None, 1 Sub, 2 Up, 3 Average, 4 Paeth) of a PNG this
    module decodes; None for any other file."""
    inflated = _inflated_rows(data)
    return None if inflated is None else inflated[2][:, 0].copy()


def _inflated_rows(data: bytes | memoryview) -> tuple[tuple[int, ...], np.ndarray, np.ndarray] | None:
    """(IHDR fields, the inflated bytes, their (H, 1 + W * channels) rows) of an 8-bit grey or RGB,
    non-interlaced PNG without palette or transparency; None for anything else or a damaged file."""
    view = memoryview(data)
    if bytes(view[:8]) != PNG_SIGNATURE:
        return None
    header, idat = None, []
    pos = 8
    while pos + 8 <= len(view):
        length, kind = struct.unpack_from(">I4s", view, pos)
        body = view[pos + 8 : pos + 8 + length]
        if kind == b"IHDR":
            header = struct.unpack_from(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
        elif kind in _BAIL_CHUNKS:
            return None
        pos += 12 + length
    if header is None or not idat:
        return None
    width, height, depth, colour, _compression, _filter_method, interlace = header
    if depth != 8 or interlace != 0 or colour not in (_GREY, _RGB) or width == 0 or height == 0:
        return None
    channels = 1 if colour == _GREY else 3
    try:
        raw = np.frombuffer(_inflater.decompress(b"".join(idat)), np.uint8)
    except (_inflater.error, zlib.error, ValueError):  # isal raises its own IsalError
        return None
    stride = width * channels + 1
    if raw.size < height * stride:
        return None
    return header, raw, raw[: height * stride].reshape(height, stride)


def _row_prefix_sums(pixels: np.ndarray) -> np.ndarray:
    """(H, W, C) uint8 -> the running sum along each row, per channel, mod 256 (a new array).

    By doubling: after the pass with step s every pixel holds the sum of the 2s pixels ending at
    it, so log2(W) whole-array uint8 additions (SIMD, no Python loop over rows) give the prefix
    sum; at 720p that is 11 passes. Each pass writes into the other of two buffers: added in
    place, the overlapping operands would make NumPy copy one of them first (~0.85 ms a 720p
    frame this way, ~1.3 ms in place, ~2 ms for np.cumsum, which runs one element at a time).
    uint8 arithmetic wraps, which is the mod 256 the filter asks for.
    """
    current = np.array(pixels, np.uint8, order="C")
    other = np.empty_like(current)
    step = 1
    while step < current.shape[1]:
        np.add(current[:, step:], current[:, :-step], out=other[:, step:])
        other[:, :step] = current[:, :step]
        current, other = other, current
        step *= 2
    return current


def _unfiltered_by_libpng(header: tuple[int, ...], inflated: np.ndarray) -> np.ndarray | None:
    """OpenCV's decoding of a PNG rebuilt from its IHDR fields and its already inflated rows, stored uncompressed."""
    png = b"".join((PNG_SIGNATURE, _chunk(b"IHDR", struct.pack(">IIBBBBB", *header)),
                    _chunk(b"IDAT", _stored_zlib_stream(memoryview(inflated))), _chunk(b"IEND", b"")))
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    return image if image is not None and image.dtype == np.uint8 and image.ndim in (2, 3) else None


_STORED_BLOCK = 65535  # the most a deflate "stored" block holds


def _stored_zlib_stream(data: memoryview) -> bytes:
    """`data` as a zlib stream of stored deflate blocks, built by hand: zlib.compress(data, 0) does the
    same in ~0.8 ms a 720p frame, the headers and ISA-L's Adler-32 here in ~0.1."""
    parts = [b"\x78\x01"]  # zlib header: deflate, 32 KB window, no dictionary
    for start in range(0, max(len(data), 1), _STORED_BLOCK):
        block = data[start : start + _STORED_BLOCK]
        final = start + _STORED_BLOCK >= len(data)
        parts += (struct.pack("<BHH", final, len(block), len(block) ^ 0xFFFF), block)
    parts.append(struct.pack(">I", _inflater.adler32(data) & 0xFFFFFFFF))
    return b"".join(parts)


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", _inflater.crc32(body, _inflater.crc32(kind)) & 0xFFFFFFFF)
