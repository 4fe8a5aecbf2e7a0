"""Printable boards: the vector files draw exactly OpenCV's board, at true size, and detect fully."""

from __future__ import annotations

import re
import shutil
import struct
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibcoach.app.outputs.board_print import (
    MARGIN_MM,
    PT_PER_MM,
    board_raster,
    board_rectangles_mm,
    caption_lines,
    write_board,
)
from calibcoach.coverage.board import BoardSpec
from calibcoach.drivers.errors import CalibcoachError

PX_PER_MM = 10.0
SPECS = {
    "default": BoardSpec(),  # 30.01 / 22.01 mm: cell edges fall between pixels, OpenCV rounds them
    "exact": BoardSpec(squares_x=6, squares_y=8, square_mm=30.0, marker_mm=21.0, dictionary="DICT_4X4_50"),  # 3.5 mm cells
    "legacy": BoardSpec(squares_x=5, squares_y=6, legacy=True),  # even row count: the legacy layout differs
    "modern": BoardSpec(squares_x=5, squares_y=6, legacy=False),
    "6x6": BoardSpec(squares_x=5, squares_y=7, square_mm=40.0, marker_mm=30.0, dictionary="DICT_6X6_250"),
    "inverted": BoardSpec(squares_x=5, squares_y=7, inverted=True),
}
SVG_NS = "{http://www.w3.org/2000/svg}"


def rasterise(rects_mm: np.ndarray, shape: tuple[int, int], *, background: int, ink: int) -> np.ndarray:
    """Rectangles (x, y, w, h) mm -> image at PX_PER_MM; a pixel is ink when its centre is inside a rectangle.

    Edges are snapped to 1e-4 px first: the PDF's 6-decimal points move an edge lying
    exactly on a pixel centre by ~4e-7 mm, which would otherwise open one-pixel seams between cells.
    """
    img = np.full(shape, background, np.uint8)
    for x, y, w, h in rects_mm:
        x0, x1 = (int(np.ceil(round(v * PX_PER_MM, 4) - 0.5)) for v in (x, x + w))
        y0, y1 = (int(np.ceil(round(v * PX_PER_MM, 4) - 0.5)) for v in (y, y + h))
        img[y0:y1, x0:x1] = ink
    return img


def detected_corners(board_img: np.ndarray, spec: BoardSpec) -> int:
    """ChArUco corners found in a board image (inverted prints are inverted back, as the detector would)."""
    grey = 255 - board_img if spec.inverted else board_img
    padded = cv2.copyMakeBorder(grey, 60, 60, 60, 60, cv2.BORDER_CONSTANT, value=255)
    _, ids, _, _ = cv2.aruco.CharucoDetector(spec.cv_board()).detectBoard(padded)
    return 0 if ids is None else len(ids)


def svg_board(path: Path) -> tuple[ET.Element, np.ndarray, int, int]:
    """The SVG's root, its ink rectangles in board millimetres, and the ink / paper grey levels."""
    root = ET.parse(path).getroot()
    group = root.find(f"{SVG_NS}g[@id='ink']")
    paper = root.find(f"{SVG_NS}rect[@id='board']").get("fill")
    rects = [[float(r.get(k)) for k in ("x", "y", "width", "height")] for r in group.iter(f"{SVG_NS}rect")]
    grey = {"#000000": 0, "#ffffff": 255}
    return root, np.asarray(rects) - [MARGIN_MM, MARGIN_MM, 0, 0], grey[group.get("fill")], grey[paper]


def pdf_parts(data: bytes) -> dict:
    """Check the PDF's structure (xref offsets, stream length, trailer) and return its pieces."""
    assert data.startswith(b"%PDF-1.4\n") and data.rstrip().endswith(b"%%EOF")
    startxref = int(re.search(rb"startxref\n(\d+)\n%%EOF", data).group(1))
    assert data[startxref:].startswith(b"xref\n0 7\n")
    offsets = [int(m) for m in re.findall(rb"(\d{10}) 00000 n ", data[startxref:])]
    assert len(offsets) == 6
    for number, offset in enumerate(offsets, start=1):
        assert data[offset:].startswith(b"%d 0 obj\n" % number)
    assert re.search(rb"trailer\n<< /Size 7 /Root 1 0 R /Info 6 0 R >>", data)
    length = int(re.search(rb"<< /Length (\d+) >>\nstream\n", data).group(1))
    start = data.index(b"stream\n") + len(b"stream\n")
    assert data[start + length :].startswith(b"endstream")
    media = [float(v) for v in re.search(rb"/MediaBox \[0 0 ([\d.]+) ([\d.]+)\]", data).groups()]
    return {"content": data[start : start + length].decode("ascii"), "media_pt": media, "raw": data}


def pdf_board(content: str, page_h_pt: float) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Filled rectangles per fill colour ("0 g" black / "1 g" white) in board millimetres, and the texts."""
    rects: dict[str, list[list[float]]] = {"0": [], "1": []}
    colour = "0"
    for line in content.splitlines():
        if line in ("0 g", "1 g"):
            colour = line[0]
        elif line.endswith(" re"):
            x, y, w, h = (float(v) / PT_PER_MM for v in line.split()[:4])
            rects[colour].append([x - MARGIN_MM, page_h_pt / PT_PER_MM - y - h - MARGIN_MM, w, h])
    texts = [re.sub(r"\\(.)", r"\1", t) for t in re.findall(r"\((.*)\) Tj", content)]  # undo PDF string escapes
    return np.asarray(rects["0"]).reshape(-1, 4), np.asarray(rects["1"]).reshape(-1, 4), texts


@pytest.mark.parametrize("name", list(SPECS))
def test_svg_draws_opencvs_board_at_true_size(tmp_path: Path, name: str) -> None:
    spec = SPECS[name]
    root, rects, ink, paper = svg_board(write_board(tmp_path / "board.svg", spec))
    width_mm, height_mm = spec.size_mm
    assert root.get("width") == f"{width_mm + 30:g}mm" and root.get("height") == f"{height_mm + 30:g}mm"
    assert root.get("viewBox") == f"0 0 {width_mm + 30:g} {height_mm + 30:g}"  # 1 user unit = 1 mm
    reference = board_raster(spec, px_per_mm=PX_PER_MM)
    drawn = rasterise(rects, reference.shape, background=paper, ink=ink)
    agreement = float((drawn == reference).mean())
    assert agreement > (0.9999 if name == "exact" else 0.995)
    assert detected_corners(drawn, spec) == spec.corner_count
    assert (ink, paper) == ((255, 0) if spec.inverted else (0, 255))


@pytest.mark.parametrize("name", list(SPECS))
def test_pdf_is_well_formed_and_draws_opencvs_board(tmp_path: Path, name: str) -> None:
    spec = SPECS[name]
    parts = pdf_parts(write_board(tmp_path / "board.pdf", spec).read_bytes())
    width_mm, height_mm = spec.size_mm
    np.testing.assert_allclose(parts["media_pt"], [(width_mm + 30) * 72 / 25.4, (height_mm + 30) * 72 / 25.4], atol=1e-5)
    assert b"/BaseFont /Helvetica" in parts["raw"] and b"/PrintScaling /None" in parts["raw"]
    black, white, texts = pdf_board(parts["content"], parts["media_pt"][1])
    reference = board_raster(spec, px_per_mm=PX_PER_MM)
    if spec.inverted:  # one black rectangle for the whole board, then the (white) ink
        np.testing.assert_allclose(black, [[0, 0, width_mm, height_mm]], atol=1e-5)
        drawn = rasterise(white, reference.shape, background=0, ink=255)
    else:
        assert white.size == 0
        drawn = rasterise(black, reference.shape, background=255, ink=0)
    assert float((drawn == reference).mean()) > (0.9999 if name == "exact" else 0.995)
    assert detected_corners(drawn, spec) == spec.corner_count
    assert texts == list(caption_lines(spec))
    assert "print at 100% / actual size" in texts[1].lower() and "--square-mm" in texts[1]
    assert f"squares {spec.square_mm:g} mm" in texts[0] and spec.dictionary in texts[0]


def test_rectangles_count_squares_and_marker_cells() -> None:
    spec = SPECS["exact"]  # 6 x 8 squares, 24 markers of 4x4 bits + a one-cell border: 21 mm / 6 = 3.5 mm cells
    rects = board_rectangles_mm(spec)
    squares = rects[np.isclose(rects[:, 2], 30.0)]
    cells = rects[np.isclose(rects[:, 2], 3.5)]
    assert len(squares) == 24 and len(cells) == len(rects) - 24
    assert 24 * 20 <= len(cells) <= 24 * 36  # every marker has its 20 border cells plus some black bits
    first_row = cells[cells[:, 1] < 30.0]
    assert first_row[:, 0].min() == pytest.approx(30.0 + 4.5)  # the top-left square is black: the first marker sits in (0, 1)
    assert first_row[:, 1].min() == pytest.approx(4.5)  # ... centred: (30 - 21) / 2 from the square's edge
    legacy, modern = board_rectangles_mm(SPECS["legacy"]), board_rectangles_mm(SPECS["modern"])
    shape = (int(6 * 30.01 * PX_PER_MM), int(5 * 30.01 * PX_PER_MM))
    difference = (rasterise(legacy, shape, background=255, ink=0) != rasterise(modern, shape, background=255, ink=0)).mean()
    assert difference > 0.3  # the two layouts really differ, so the agreement tests above tell them apart


@pytest.mark.skipif(shutil.which("pdftoppm") is None, reason="poppler's pdftoppm is not installed")
@pytest.mark.parametrize("name", ["default", "exact", "inverted"])
def test_pdf_renders_like_opencvs_raster(tmp_path: Path, name: str) -> None:
    spec = SPECS[name]
    pdf = write_board(tmp_path / "board.pdf", spec)
    dpi = 25.4 * PX_PER_MM  # 254 dpi: 10 px per mm
    subprocess.run(["pdftoppm", "-r", f"{dpi:g}", "-gray", str(pdf), str(tmp_path / "page")], check=True, capture_output=True)
    page = cv2.imread(str(tmp_path / "page-1.pgm"), cv2.IMREAD_GRAYSCALE)
    width_mm, height_mm = spec.size_mm
    assert abs(page.shape[1] - (width_mm + 30) * PX_PER_MM) <= 1 and abs(page.shape[0] - (height_mm + 30) * PX_PER_MM) <= 1
    reference = board_raster(spec, px_per_mm=PX_PER_MM)
    margin = int(MARGIN_MM * PX_PER_MM)
    board = page[margin : margin + reference.shape[0], margin : margin + reference.shape[1]]
    assert float(((board < 128) == (reference < 128)).mean()) > 0.995
    assert detected_corners(np.where(board < 128, 0, 255).astype(np.uint8), spec) == spec.corner_count
    caption = page[margin + reference.shape[0] + 20 :, margin:]
    assert (caption < 128).sum() > 2000  # the caption is printed in the bottom margin


@pytest.mark.parametrize("dpi", [150, 300])
def test_png_is_opencvs_raster_at_the_dpi_with_caption(tmp_path: Path, dpi: int) -> None:
    spec = SPECS["default"]
    path = write_board(tmp_path / "board.png", spec, dpi=dpi)
    data = path.read_bytes()
    assert data[12:16] == b"IHDR" and data[37:41] == b"pHYs"
    ppm_x, ppm_y, unit = struct.unpack(">IIB", data[41:50])
    assert (ppm_x, ppm_y, unit) == (round(dpi / 0.0254), round(dpi / 0.0254), 1)
    page = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    px_per_mm = dpi / 25.4
    margin = round(MARGIN_MM * px_per_mm)
    reference = board_raster(spec, px_per_mm=px_per_mm)
    assert page.shape == (reference.shape[0] + 2 * margin, reference.shape[1] + 2 * margin)
    assert reference.shape == (round(330.11 * px_per_mm), round(240.08 * px_per_mm))
    np.testing.assert_array_equal(page[margin : margin + reference.shape[0], margin : margin + reference.shape[1]], reference)
    assert (page[margin + reference.shape[0] + 5 :, :] < 128).sum() > 500  # caption
    assert detected_corners(page, spec) == spec.corner_count


def test_inverted_png_is_white_on_black(tmp_path: Path) -> None:
    spec = SPECS["inverted"]
    page = cv2.imread(str(write_board(tmp_path / "board.png", spec, dpi=150)), cv2.IMREAD_GRAYSCALE)
    normal = board_raster(BoardSpec(squares_x=5, squares_y=7, inverted=False), px_per_mm=150 / 25.4)
    margin = round(MARGIN_MM * 150 / 25.4)
    board = page[margin : margin + normal.shape[0], margin : margin + normal.shape[1]]
    np.testing.assert_array_equal(board, 255 - normal)
    assert page[5, 5] == 255  # the paper around the board stays white


def test_unknown_extension_is_refused(tmp_path: Path) -> None:
    with pytest.raises(CalibcoachError, match=r"use a .svg, .pdf or .png file name"):
        write_board(tmp_path / "board.jpg", BoardSpec())
    with pytest.raises(CalibcoachError, match="outside 50..2400"):
        write_board(tmp_path / "board.png", BoardSpec(), dpi=10)
