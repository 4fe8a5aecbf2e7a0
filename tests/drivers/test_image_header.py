"""Image sizes from file headers (drivers/image_header.py) agree with what OpenCV decodes."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibcoach.drivers.image_header import header_size


def _image(width: int, height: int) -> np.ndarray:
    return np.random.default_rng(0).integers(0, 255, (height, width, 3), np.uint8)


@pytest.mark.parametrize(("name", "params"), [
    ("a.png", []), ("grey.png", None), ("a.jpg", []), ("progressive.jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]),
])
def test_png_and_jpeg_sizes_match_the_decoded_image(tmp_path: Path, name: str, params: list[int] | None) -> None:
    path = tmp_path / name
    image = _image(77, 33)
    assert cv2.imwrite(str(path), image[:, :, 0] if params is None else image, params or [])
    assert header_size(path) == (77, 33) == tuple(cv2.imread(str(path)).shape[1::-1])


def test_a_jpeg_thumbnail_inside_exif_is_not_taken_for_the_image(tmp_path: Path) -> None:
    ok, thumb = cv2.imencode(".jpg", _image(16, 12))
    ok2, main = cv2.imencode(".jpg", _image(120, 90))
    assert ok and ok2
    # an APP1 segment holding a whole JPEG (its own SOF says 16x12) between SOI and the image's segments
    app1 = b"Exif\x00\x00" + thumb.tobytes()
    data = main.tobytes()[:2] + b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1 + main.tobytes()[2:]
    path = tmp_path / "exif.jpg"
    path.write_bytes(data)
    assert header_size(path) == (120, 90) == tuple(cv2.imread(str(path)).shape[1::-1])


def test_other_formats_and_broken_headers_give_none(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "a.bmp"), _image(8, 8))
    (tmp_path / "cut.jpg").write_bytes(b"\xff\xd8\xff\xe0\x00")
    (tmp_path / "cut.png").write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00")
    (tmp_path / "empty.png").write_bytes(b"")
    for name in ("a.bmp", "cut.jpg", "cut.png", "empty.png", "missing.png"):
        assert header_size(tmp_path / name) is None, name
