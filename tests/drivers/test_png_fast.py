"""The fast PNG decoder gives OpenCV's pixels exactly, declines what it does not handle, and a
folder of OpenCV-written PNGs replays through it with the frames OpenCV would give -- both with
the C unfilter the install builds and with the NumPy and libpng fallback used where it is not built."""

from __future__ import annotations

import importlib.util
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibcoach.drivers import png_fast
from calibcoach.drivers.png_fast import decode_png
from calibcoach.drivers.replay import ImageFolderSource


@pytest.fixture(autouse=True, params=["C unfilter", "NumPy and libpng"])
def unfilter_path(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Every test runs on both ways of undoing the row filters."""
    if request.param == "NumPy and libpng":
        monkeypatch.setattr(png_fast, "_unfilter_in_c", None)
    return request.param


def test_the_c_unfilter_was_built() -> None:
    assert importlib.util.find_spec("calibcoach.drivers._png_unfilter") is not None, (
        "calibcoach.drivers._png_unfilter did not build (pyproject ext-modules): install a C compiler and the "
        "Python headers, then `pip install -e .` again; decoding falls back on NumPy and libpng, ~2x slower")


def test_an_unknown_row_filter_is_declined_not_misread() -> None:
    data = _handmade(np.random.default_rng(6).integers(0, 256, (9, 11), dtype=np.uint8), 5)  # types end at 4
    assert decode_png(data) is None


def _cv(data: bytes, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(data, np.uint8), flags)


def _png(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)


def _handmade(pixels: np.ndarray, filter_type: int) -> bytes:
    """An 8-bit grey PNG whose rows all carry `filter_type` (the bytes stored raw: a wrong filter decodes wrong)."""
    return _handmade_rows(pixels, np.full(pixels.shape[0], filter_type))


@pytest.mark.parametrize("shape", [(720, 1280), (37, 53), (1, 1), (45, 80, 3), (3, 2, 3)])
def test_opencv_written_pngs_decode_to_opencvs_pixels(shape: tuple[int, ...]) -> None:
    rng = np.random.default_rng(sum(shape))
    image = rng.integers(0, 256, shape, dtype=np.uint8)
    image[: shape[0] // 2] //= 7  # smooth and noisy parts, so the encoder's choices vary
    ok, encoded = cv2.imencode(".png", image)
    assert ok
    fast = decode_png(encoded.tobytes())
    assert fast is not None, "OpenCV's own PNGs (every row Sub-filtered) are what the fast path is for"
    assert fast.dtype == np.uint8 and fast.shape == shape
    assert np.array_equal(fast, _cv(encoded.tobytes()))


def test_rows_without_a_filter_decode_too() -> None:
    pixels = np.random.default_rng(1).integers(0, 256, (9, 11), dtype=np.uint8)
    data = _handmade(pixels, 0)
    assert np.array_equal(decode_png(data), pixels)
    assert np.array_equal(_cv(data), pixels)


@pytest.mark.parametrize("filter_type", [2, 3, 4])  # Up, Average, Paeth: other encoders' choices
def test_other_filters_are_unfiltered_by_libpng_to_opencvs_pixels(filter_type: int) -> None:
    data = _handmade(np.random.default_rng(2).integers(0, 256, (9, 11), dtype=np.uint8), filter_type)
    fast = decode_png(data)
    assert fast is not None
    assert np.array_equal(fast, _cv(data))


@pytest.mark.parametrize("shape", [(720, 1280), (45, 80, 3)])
def test_libpngs_adaptive_filters_decode_to_opencvs_pixels(shape: tuple[int, ...]) -> None:
    """OpenCV 5.1 with an explicit compression level writes rows of every filter type."""
    rng = np.random.default_rng(7)
    image = cv2.GaussianBlur(rng.integers(0, 256, shape, dtype=np.uint8), (5, 5), 1.5)  # smooth: Avg and Paeth win
    ok, encoded = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    assert ok
    data = encoded.tobytes()
    fast = decode_png(data)
    assert fast is not None and fast.shape == shape
    assert np.array_equal(fast, _cv(data))


@pytest.mark.parametrize("shape", [(721, 1280), (64, 97), (2, 5), (33, 41, 3)])
def test_rows_of_mixed_filters_decode_to_libpngs_pixels(shape: tuple[int, ...]) -> None:
    # Every filter, each row its own, in runs of Average and Paeth (which the C loop undoes two
    # rows at a time) with odd heights (a row left over); the stored bytes are random, so the
    # Paeth predictor meets every kind of neighbourhood (~1.8 million at 721 x 1280) and any
    # departure from libpng's choice shows.
    rng = np.random.default_rng(shape[0])
    filters = rng.choice([3, 4], size=shape[0])  # Average and Paeth, in runs
    other = rng.random(shape[0]) < 0.25
    filters[other] = rng.integers(0, 3, int(other.sum()))  # None, Sub and Up now and then
    data = _handmade_rows(rng.integers(0, 256, shape, dtype=np.uint8), filters)
    fast = decode_png(data)
    assert fast is not None and fast.shape == shape
    assert np.array_equal(fast, _cv(data))


def _handmade_rows(pixels: np.ndarray, filters: np.ndarray) -> bytes:
    """An 8-bit grey or RGB PNG with row y filtered by `filters[y]` (the bytes stored raw)."""
    h, w = pixels.shape[:2]
    channels = 1 if pixels.ndim == 2 else 3
    rows = np.concatenate([filters.astype(np.uint8).reshape(h, 1), pixels.reshape(h, w * channels)], axis=1)
    colour = 0 if channels == 1 else 2
    return (b"\x89PNG\r\n\x1a\n" + _png(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, colour, 0, 0, 0))
            + _png(b"IDAT", zlib.compress(rows.tobytes())) + _png(b"IEND", b""))


def test_what_it_does_not_handle_is_declined() -> None:
    grey = np.random.default_rng(3).integers(0, 256, (20, 30), dtype=np.uint8)
    declined = {
        "16-bit": cv2.imencode(".png", grey.astype(np.uint16) * 257)[1].tobytes(),
        "alpha": cv2.imencode(".png", np.dstack([grey] * 4))[1].tobytes(),
        "JPEG": cv2.imencode(".jpg", grey)[1].tobytes(),
        "empty": b"",
    }
    for name, data in declined.items():
        assert decode_png(data) is None, name


def test_a_damaged_png_is_declined_not_misread() -> None:
    grey = np.random.default_rng(4).integers(0, 256, (64, 64), dtype=np.uint8)
    data = bytearray(cv2.imencode(".png", grey)[1].tobytes())
    data[len(data) // 2] ^= 0xFF  # inside the compressed pixels: their Adler-32 no longer matches
    assert decode_png(bytes(data)) is None
    truncated = bytes(data[: len(data) // 3])
    assert decode_png(truncated) is None


def test_a_folder_of_opencv_pngs_replays_with_opencvs_frames(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    greys = [rng.integers(0, 256, (48, 64), dtype=np.uint8) for _ in range(5)]
    for n, grey in enumerate(greys):
        cv2.imwrite(str(tmp_path / f"{n}.png"), grey)
    source = ImageFolderSource(tmp_path)
    assert source._fast_png  # noqa: SLF001 - the folder's first image decided the decoder
    frames = list(source)
    assert [f.image.shape for f in frames] == [(48, 64)] * 5
    assert all(np.array_equal(f.image, g) for f, g in zip(frames, greys, strict=True))


@pytest.mark.parametrize("shape", [(7, 13), (7, 13, 3), (1, 1), (1, 1, 3), (48, 1, 3), (720, 1280, 3)])
def test_encoded_pngs_give_the_pixels_back_to_opencv_and_here(shape: tuple[int, ...]) -> None:
    image = np.random.default_rng(sum(shape)).integers(0, 256, shape, dtype=np.uint8)  # noise: any lossy step shows
    data = png_fast.encode_png(image)
    assert np.array_equal(_cv(data), image)  # libpng checks the chunks' CRCs and the zlib stream's Adler-32
    assert np.array_equal(decode_png(data), image)
    assert png_fast.row_filters(data).tolist() == [1] * shape[0]  # every row Sub: the fast path on replay


def test_encode_png_refuses_what_a_png_frame_cannot_be() -> None:
    for bad in (np.zeros((4, 4), np.uint16), np.zeros((4, 4, 4), np.uint8), np.zeros((0, 4), np.uint8)):
        with pytest.raises(ValueError, match=r"encode_png takes \(H, W\) or \(H, W, 3\) uint8 images"):
            png_fast.encode_png(bad)
