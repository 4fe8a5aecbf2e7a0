"""Printable ChArUco boards: vector SVG and PDF at true scale, and a PNG raster at a chosen dpi.

The board's geometry comes from OpenCV's own `CharucoBoard` (which squares hold markers, which
marker id sits where, the legacy pattern of OpenCV < 4.6), so a print always matches what the
detector expects. The vector files draw one filled rectangle per black square and per black marker
cell, in millimetres, so they print at the board's exact size; the PDF is written by hand (PDF 1.4,
one page, standard Helvetica, no dependency) because the project has no PDF library.

Every print carries a caption with the board's sizes and dictionary and the instruction that
matters most: print at 100 % / actual size, then measure a square and pass --square-mm (the solver
treats the board's sizes as truth).
"""

from __future__ import annotations

import struct
import zlib
from datetime import UTC, datetime
from pathlib import Path

import cv2
import numpy as np

from calibcoach.app.outputs.files import atomic_write_bytes
from calibcoach.coverage.board import BoardSpec
from calibcoach.drivers.errors import CalibcoachError

MARGIN_MM = 15.0  # white paper around the board: room for the caption and for the printer's dead zone
PT_PER_MM = 72.0 / 25.4
_CAPTION_PT = 8.0  # caption size, shrunk when the board is too narrow for it
# Helvetica advance widths (1/1000 em) for ASCII 32..126, from Adobe's AFM (standard 14 font metrics).
_HELVETICA = (
    [278, 278, 355, 556, 556, 889, 667, 191, 333, 333, 389, 584, 278, 333, 278, 278]
    + [556] * 10
    + [278, 278, 584, 584, 584, 556, 1015, 667, 667, 722, 722, 667, 611, 778, 722, 278, 500, 667, 556, 833]
    + [722, 778, 667, 778, 722, 667, 611, 722, 667, 944, 667, 667, 611, 278, 278, 278, 469, 556, 333]
    + [556, 556, 500, 556, 556, 278, 556, 556, 222, 222, 500, 222, 833, 556, 556, 556, 556, 333, 500]
    + [278, 556, 500, 722, 500, 500, 500, 334, 260, 334, 584]
)


def board_rectangles_mm(spec: BoardSpec) -> np.ndarray:
    """The ink of a normal (black-on-white) print: black squares and black marker cells.

    Squares without a marker are black; each marker is centred in its square and drawn from its
    dictionary bit pattern with a one-cell black border (`borderBits=1`, OpenCV's default).

    Returns:
        (R, 4) float64 rectangles (x, y, width, height) in millimetres in the board frame: origin at
        the outer corner of the top-left square, x right, y down (the image's orientation).
    """
    board = spec.cv_board()
    corners = np.asarray(board.getObjPoints(), np.float64).reshape(-1, 4, 3) * 1000.0  # (M, 4, 3) mm
    ids = np.asarray(board.getIds()).reshape(-1)
    dictionary = board.getDictionary()
    cells = dictionary.markerSize + 2
    sq, mk = spec.square_mm, spec.marker_mm
    cell = mk / cells
    offset = (sq - mk) / 2.0
    rects: list[tuple[float, float, float, float]] = []
    with_marker: set[tuple[int, int]] = set()
    for marker_id, quad in zip(ids, corners, strict=True):
        col, row = (int(v) for v in np.floor(quad[:, :2].mean(axis=0) / sq))
        with_marker.add((row, col))
        x0, y0 = col * sq + offset, row * sq + offset
        bits = dictionary.generateImageMarker(int(marker_id), cells, borderBits=1)  # one pixel per cell
        for r, c in zip(*np.nonzero(bits < 128), strict=True):
            rects.append((x0 + c * cell, y0 + r * cell, cell, cell))
    squares = [
        (col * sq, row * sq, sq, sq)
        for row in range(spec.squares_y)
        for col in range(spec.squares_x)
        if (row, col) not in with_marker
    ]
    return np.asarray(squares + rects, np.float64).reshape(-1, 4)


def caption_lines(spec: BoardSpec) -> tuple[str, str]:
    """The two caption lines printed under the board (ASCII, so every font and format can show them)."""
    extras = [x for x, on in (("legacy pattern", spec.legacy), ("inverted: white on black", spec.inverted)) if on]
    first = (
        f"ChArUco {spec.squares_x} x {spec.squares_y} squares, {spec.dictionary}, squares {spec.square_mm:g} mm, "
        f"markers {spec.marker_mm:g} mm" + (f" ({', '.join(extras)})" if extras else "")
    )
    second = "Print at 100% / actual size (no fit to page), then measure a square and pass --square-mm (and --marker-mm)."
    return first, second


def write_board(path: str | Path, spec: BoardSpec, *, dpi: float = 300.0) -> Path:
    """Write a printable board; the extension picks the format: .svg, .pdf (vector) or .png (raster).

    The page is the board plus `MARGIN_MM` on every side. `dpi` applies to .png only; the PNG records
    it (pHYs chunk) so that image viewers print it at true size too.

    Raises:
        CalibcoachError: an unknown extension.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".svg":
        return atomic_write_bytes(path, _svg(spec).encode("utf-8"))
    if suffix == ".pdf":
        return atomic_write_bytes(path, _pdf(spec))
    if suffix == ".png":
        return atomic_write_bytes(path, _png(spec, dpi))
    raise CalibcoachError(f"cannot print a board to {path.name}: use a .svg, .pdf or .png file name")


def _num(value: float) -> str:
    """Fixed-point number with trailing zeros removed (SVG and PDF both accept it)."""
    text = f"{value:.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def _page_mm(spec: BoardSpec) -> tuple[float, float]:
    width, height = spec.size_mm
    return width + 2 * MARGIN_MM, height + 2 * MARGIN_MM


def _caption_size_pt(spec: BoardSpec) -> float:
    """The caption's font size: `_CAPTION_PT`, or less when the longest line is wider than the board."""
    widest = max(sum(_HELVETICA[ord(ch) - 32] if 32 <= ord(ch) < 127 else 556 for ch in line) for line in caption_lines(spec))
    available_pt = (spec.size_mm[0] + MARGIN_MM) * PT_PER_MM
    return min(_CAPTION_PT, available_pt / (widest / 1000.0))


def _caption_baselines_mm(spec: BoardSpec) -> tuple[float, float]:
    """Caption baselines in page millimetres from the top: in the bottom margin, 5 and 9.5 mm below the board."""
    bottom = MARGIN_MM + spec.size_mm[1]
    return bottom + 5.0, bottom + 9.5


def _svg(spec: BoardSpec) -> str:
    page_w, page_h = _page_mm(spec)
    board_w, board_h = spec.size_mm
    ink, paper = ("#ffffff", "#000000") if spec.inverted else ("#000000", "#ffffff")
    lines = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{_num(page_w)}mm" height="{_num(page_h)}mm" '
        f'viewBox="0 0 {_num(page_w)} {_num(page_h)}">',
        f"<title>{_xml(caption_lines(spec)[0])}</title>",
        f'<rect x="0" y="0" width="{_num(page_w)}" height="{_num(page_h)}" fill="#ffffff"/>',
        f'<rect id="board" x="{_num(MARGIN_MM)}" y="{_num(MARGIN_MM)}" width="{_num(board_w)}" height="{_num(board_h)}" fill="{paper}"/>',
        f'<g id="ink" fill="{ink}" shape-rendering="crispEdges">',
    ]
    for x, y, w, h in board_rectangles_mm(spec):
        lines.append(f'<rect x="{_num(x + MARGIN_MM)}" y="{_num(y + MARGIN_MM)}" width="{_num(w)}" height="{_num(h)}"/>')
    lines.append("</g>")
    size_mm = _caption_size_pt(spec) / PT_PER_MM
    for text, baseline in zip(caption_lines(spec), _caption_baselines_mm(spec), strict=True):
        lines.append(
            f'<text x="{_num(MARGIN_MM)}" y="{_num(baseline)}" font-family="Helvetica, Arial, sans-serif" '
            f'font-size="{_num(size_mm)}" fill="#000000">{_xml(text)}</text>'
        )
    lines.append("</svg>")
    return "\n".join(lines) + "\n"


def _xml(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace('"', "&quot;")


def _pdf_text(text: str) -> str:
    clean = text.encode("ascii", "replace").decode("ascii")
    return clean.replace("\\", "\\\\").replace("(", "\\(").replace(")", "\\)")


def _pdf(spec: BoardSpec) -> bytes:
    """A one-page PDF 1.4: the board's rectangles as one filled path (no seams between cells), then the caption."""
    page_w, page_h = (v * PT_PER_MM for v in _page_mm(spec))
    board_w, board_h = spec.size_mm

    def rect_pt(x_mm: float, y_mm: float, w_mm: float, h_mm: float) -> str:
        # PDF's origin is the page's bottom-left corner with y up; the board frame has y down.
        x = (x_mm + MARGIN_MM) * PT_PER_MM
        y = page_h - (y_mm + MARGIN_MM + h_mm) * PT_PER_MM
        return f"{_num(x)} {_num(y)} {_num(w_mm * PT_PER_MM)} {_num(h_mm * PT_PER_MM)} re"

    ops = ["q"]
    if spec.inverted:
        ops += ["0 g", rect_pt(0, 0, board_w, board_h), "f", "1 g"]
    else:
        ops.append("0 g")
    ops += [rect_pt(*r) for r in board_rectangles_mm(spec)]
    ops += ["f", "Q", "0 g"]
    size = _caption_size_pt(spec)
    for text, baseline in zip(caption_lines(spec), _caption_baselines_mm(spec), strict=True):
        ops.append(f"BT /F1 {_num(size)} Tf {_num(MARGIN_MM * PT_PER_MM)} {_num(page_h - baseline * PT_PER_MM)} Td ({_pdf_text(text)}) Tj ET")
    content = ("\n".join(ops) + "\n").encode("ascii")
    created = datetime.now(UTC).strftime("D:%Y%m%d%H%M%SZ")
    objects = [
        # PrintScaling /None asks viewers to default to "actual size" in their print dialogue.
        b"<< /Type /Catalog /Pages 2 0 R /ViewerPreferences << /PrintScaling /None >> >>",
        b"<< /Type /Pages /Kids [3 0 R] /Count 1 >>",
        f"<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {_num(page_w)} {_num(page_h)}] "
        "/Resources << /Font << /F1 4 0 R >> >> /Contents 5 0 R >>".encode("ascii"),
        b"<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica /Encoding /WinAnsiEncoding >>",
        b"<< /Length %d >>\nstream\n" % len(content) + content + b"endstream",
        f"<< /Title ({_pdf_text(caption_lines(spec)[0])}) /Creator (calibcoach) /CreationDate ({created}) >>".encode("ascii"),
    ]
    out = bytearray(b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n")
    offsets = []
    for number, body in enumerate(objects, start=1):
        offsets.append(len(out))
        out += b"%d 0 obj\n" % number + body + b"\nendobj\n"
    xref = len(out)
    out += b"xref\n0 %d\n0000000000 65535 f \n" % (len(objects) + 1)
    out += b"".join(b"%010d 00000 n \n" % offset for offset in offsets)
    out += b"trailer\n<< /Size %d /Root 1 0 R /Info %d 0 R >>\nstartxref\n%d\n%%%%EOF\n" % (len(objects) + 1, len(objects), xref)
    return bytes(out)


def board_raster(spec: BoardSpec, *, px_per_mm: float) -> np.ndarray:
    """The board alone (no margin) as OpenCV draws it, `px_per_mm` pixels per millimetre.

    Returns:
        (round(height_mm * px_per_mm), round(width_mm * px_per_mm)) uint8, 0 = ink (255 = ink when
        `spec.inverted`).
    """
    width_mm, height_mm = spec.size_mm
    size = (int(round(width_mm * px_per_mm)), int(round(height_mm * px_per_mm)))
    img = spec.cv_board().generateImage(size, marginSize=0, borderBits=1)
    return 255 - img if spec.inverted else img


def _png(spec: BoardSpec, dpi: float) -> bytes:
    if not 50 <= dpi <= 2400:
        raise CalibcoachError(f"board dpi {dpi:g} is outside 50..2400; pass e.g. --dpi 300")
    ppm = dpi / 25.4
    board = board_raster(spec, px_per_mm=ppm)
    margin = int(round(MARGIN_MM * ppm))
    page = np.full((board.shape[0] + 2 * margin, board.shape[1] + 2 * margin), 255, np.uint8)
    page[margin : margin + board.shape[0], margin : margin + board.shape[1]] = board
    height_px = _CAPTION_PT / PT_PER_MM * ppm * 0.72  # cap height of an 8 pt font
    for text, baseline in zip(caption_lines(spec), _caption_baselines_mm(spec), strict=True):
        scale = height_px / 22.0  # FONT_HERSHEY_SIMPLEX capitals are ~22 px tall at scale 1
        (w, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
        scale *= min(1.0, (board.shape[1] + margin) / max(w, 1))
        thickness = max(1, int(round(scale * 1.5)))
        cv2.putText(page, text, (margin, int(round(baseline * ppm))), cv2.FONT_HERSHEY_SIMPLEX, scale, 0, thickness, cv2.LINE_AA)
    ok, data = cv2.imencode(".png", page)
    if not ok:
        raise CalibcoachError(f"OpenCV could not encode the {page.shape[1]}x{page.shape[0]} board picture")
    return _with_dpi(data.tobytes(), dpi)


def _with_dpi(png: bytes, dpi: float) -> bytes:
    """Insert a pHYs chunk (pixels per metre) after IHDR so viewers and printers know the true size."""
    ppm = int(round(dpi / 0.0254))
    body = b"pHYs" + struct.pack(">IIB", ppm, ppm, 1)
    chunk = struct.pack(">I", 9) + body + struct.pack(">I", zlib.crc32(body) & 0xFFFFFFFF)
    end_of_ihdr = 8 + 8 + 13 + 4  # signature, IHDR length + type, IHDR data, CRC
    return png[:end_of_ihdr] + chunk + png[end_of_ihdr:]
