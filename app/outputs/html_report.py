"""`report.html`: the one file a person opens after a run.

Built from the same payload as `calibration.json` and the pictures already written beside it, so
it says nothing the machine-readable outputs do not. Self-contained: every picture is inlined as a
base64 PNG data URI, the CSS is inline, and there are no scripts and no external references, so it
can be mailed or attached to a ticket and opens the same anywhere. Every text that comes from the
run (reasons, frame names, the command line) goes through `html.escape`.

A refused calibration gets a report too, saying REFUSED at the top and why: it is a report, not a
camera file, so it is not one of `report.CAMERA_FILES`.
"""

from __future__ import annotations

import base64
import html
import shlex
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from calibcoach.app.outputs.files import atomic_write_bytes

__all__ = ["PICTURE_CAPTIONS", "REPORT_NAME", "render_report", "write_html_report"]

REPORT_NAME = "report.html"
WORST_FRAMES = 5
LISTED_CORNERS = 20  # dropped corners listed one by one; the rest are counted
# The pictures `report._pictures` writes, in the order the report shows them, with what each shows.
PICTURE_CAPTIONS = {
    "coverage.png": ("Coverage", "Where the board's corners were seen; hatched cells had too few."),
    "tilt_distance.png": ("Tilt and distance", "Views per tilt direction and distance against what the method needs."),
    "tilt_histogram.png": ("Tilts used", "How far the board was tilted in the frames the solve used."),
    "residuals.png": ("Residuals", "Reprojection error of every corner over the image: a pattern here is a model that does not fit."),
    "board_residuals.png": ("Residuals on the board", "Each board corner's error averaged over the poses that saw it: "
                            "long arrows that agree are the board off its spec (not flat, printed unevenly)."),
    "per_frame_errors.png": ("Per-frame errors", "RMS reprojection error of each frame used."),
    "uncertainty.png": ("Uncertainty", "Expected projection error of this calibration over the image, against its target."),
    "undistorted_check.png": ("Undistortion check", "One frame undistorted with the result: the board's lines should be straight."),
}

_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',sans-serif;margin:0 auto;max-width:1200px;padding:1.5em;color:#222;background:#fafafa}
h1{margin:.2em 0}h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
.verdict{padding:1em 1.4em;border-radius:8px;border:3px solid}
.trusted{background:#e9f7ec;border-color:#2e8b45}.refused{background:#fdecea;border-color:#c0392b}
.verdict .grade{font-size:2em;font-weight:700;margin:0}
.refused .grade{color:#c0392b}.trusted .grade{color:#1e6b32}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:.25em .6em;text-align:left;vertical-align:top}
th{background:#eee}td.num{text-align:right;font-family:ui-monospace,monospace}
figure{margin:1.2em 0}figure img{max-width:100%;height:auto;border:1px solid #ccc;background:#fff}
figcaption{color:#555;margin-top:.3em}code,pre{font-family:ui-monospace,monospace;background:#eee;padding:.1em .3em}
pre{padding:.6em;white-space:pre-wrap;word-break:break-all}.bad{color:#c0392b;font-weight:600}.small{color:#666;font-size:.9em}
"""


def write_html_report(path: Path, payload: Mapping[str, Any], pictures: Sequence[Path], *, accept_partial: bool = False) -> Path:
    """Write `report.html` from the calibration payload and the picture files; returns the path."""
    return atomic_write_bytes(path, render_report(payload, pictures, accept_partial=accept_partial).encode("utf-8"))


def render_report(payload: Mapping[str, Any], pictures: Sequence[Path], *, accept_partial: bool = False) -> str:
    """The report as one HTML document (see the module docstring)."""
    verdict = payload["verdict"]
    trusted = bool(verdict["trusted"])
    status = "TRUSTED" if trusted else "REFUSED (untrusted)"
    title = f"calibcoach report: {verdict['grade'].upper()}, {status}"
    parts = [
        "<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{_e(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{_e(title)}</h1>",
        f'<p class="small">{_e(payload["source"].get("description", ""))} &middot; {_e(payload.get("created", ""))}</p>',
        _verdict_section(verdict, accept_partial=accept_partial),
        _numbers_section(payload),
        _frames_section(payload),
        _pictures_section(pictures),
        _provenance_section(payload),
        "</body></html>",
    ]
    return "\n".join(parts) + "\n"


def _e(value: object) -> str:
    return html.escape(str(value), quote=True)


def _f(value: object, digits: int = 3) -> str:
    if value is None:
        return "&ndash;"
    number = float(value)  # type: ignore[arg-type]
    return _e(f"{number:.{digits}f}") if np.isfinite(number) else "&ndash;"


def _table(rows: Sequence[Sequence[str]], header: Sequence[str] | None = None) -> str:
    """Rows of already-escaped cells; a cell starting with '#' is a right-aligned number."""
    out = ["<table>"]
    if header:
        out.append("<tr>" + "".join(f"<th>{_e(h)}</th>" for h in header) + "</tr>")
    for row in rows:
        cells = "".join(f'<td class="num">{c[1:]}</td>' if c.startswith("#") else f"<td>{c}</td>" for c in row)
        out.append(f"<tr>{cells}</tr>")
    return "".join(out) + "</table>"


def _verdict_section(verdict: Mapping[str, Any], *, accept_partial: bool) -> str:
    trusted = bool(verdict["trusted"])
    if trusted:
        headline = f"{verdict['grade'].upper()}: trusted"
        note = "This calibration passed calibcoach's checks; its camera files are in this folder."
    else:
        headline = f"REFUSED: {verdict['grade'].upper()}, untrusted"
        note = "calibcoach refused this calibration: do not load it as a camera. " + (
            "--accept-partial was given, so its camera files were written under names carrying 'untrusted'."
            if accept_partial else "No camera files were written (--accept-partial writes them as *_untrusted).")
    reasons = "".join(f"<li>{_e(r)}</li>" for r in verdict.get("reasons", ()))
    return (f'<section id="verdict" class="verdict {"trusted" if trusted else "refused"}">'
            f'<p class="grade">{_e(headline)}</p><p>{_e(note)}</p>'
            f"<p>Why:</p><ul>{reasons or '<li>no reasons recorded</li>'}</ul>"
            f'<p class="small">RMS alone would grade it {_e(verdict.get("rms_grade", ""))}.</p></section>')


def _e_sources_row(sources: Mapping[str, Any] | None) -> list[list[str]]:
    """E from the model and from the scatter between holds (the larger is E above), when both were read."""
    if not sources or sources.get("between_holds_px") is None:
        return []
    return [["E from the corner noise / from the scatter between holds",
             f"{_f(sources.get('from_model_px'))} / {_f(sources.get('between_holds_px'))} px "
             f"<span class='small'>({int(sources.get('holds', 0))} holds; the larger is reported)</span>"]]


def _numbers_section(payload: Mapping[str, Any]) -> str:
    K = np.asarray(payload["camera_matrix"], float).reshape(3, 3)
    names = list(payload["dist_coeff_names"])
    dist = np.asarray(payload["dist_coeffs"], float).reshape(-1)
    std = payload.get("intrinsic_std", {})
    unc = payload.get("uncertainty") or {}
    cov = payload.get("coverage", {})
    w, h = payload["image_size"]
    choice = payload.get("model_choice") or {}
    e_px, target = unc.get("expected_error_px"), unc.get("target_px")
    e_cell = _f(e_px) + " px"
    if e_px is not None and target is not None and e_px > target:
        e_cell = f'<span class="bad">{e_cell}</span>'
    summary = [
        ["model", f"{_e(payload['model'])} <span class='small'>({_e(payload.get('ros_distortion_model', ''))})</span>"],
        ["image size", f"{int(w)} &times; {int(h)} px"],
        ["RMS reprojection error", f"{_f(payload['rms_px'])} px"],
        ["expected projection error E (where the board was seen)", e_cell],
        ["E target", f"{_f(target)} px"],
        *_e_sources_row(unc.get("expected_error_sources")),
        ["corner noise (per coordinate)", f"{_f(unc.get('noise_px'))} px"],
        ["uncertainty p95 covered / whole image", f"{_f(unc.get('p95_covered_px'))} / {_f(unc.get('p95_px'))} px"],
        ["coverage", f"{_f(100 * float(cov.get('completeness', 0.0)), 0)} %"],
        ["frames used / seen", f"{int(payload['frames_used'])} / {_e(cov.get('frames_seen', '?'))}"],
        ["corners used", _e(payload.get("corners_used", ""))],
    ]
    if choice:
        summary.append(["model choice", _e(choice.get("reason", ""))])
    structure = payload.get("residual_structure")
    if structure:
        summary.append(["residual fixed to the board / the image",
                        _fixed_cell(structure, "board", f" ({_f(structure.get('board_fixed_um'), 1)} um on the board)")
                        + " / " + _fixed_cell(structure, "image", "")])
    matrix = _table([[f"#{K[r, c]:.4f}" for c in range(3)] for r in range(3)])
    coeffs = _table([[_e(n), f"#{dist[i]:.6g}", f"#{std[n]:.3g}" if n in std else "&ndash;"] for i, n in enumerate(names)],
                    header=("coefficient", "value", "1-sigma"))
    focal = _table([[_e(n), f"#{K[0, 0] if n == 'fx' else K[1, 1] if n == 'fy' else K[0, 2] if n == 'cx' else K[1, 2]:.3f}",
                     f"#{std[n]:.3g}" if n in std else "&ndash;"] for n in ("fx", "fy", "cx", "cy")],
                   header=("intrinsic", "px", "1-sigma"))
    return ('<section id="numbers"><h2>The numbers</h2>' + _table(summary)
            + "<h3>Camera matrix</h3>" + matrix + focal + "<h3>Distortion coefficients</h3>" + coeffs + "</section>")


def _fixed_cell(structure: Mapping[str, Any], where: str, extra: str) -> str:
    """A residual pattern's size and its ratio to noise (residual_structure.py), in red when flagged."""
    text = (f"{_f(structure.get(f'{where}_fixed_px'))} px{extra}, "
            f"{_f(structure.get(f'{where}_fixed_ratio'), 1)}x noise's variance")
    return f'<span class="bad">{text}</span>' if structure.get(f"{where}_fixed") else text


def _frames_section(payload: Mapping[str, Any]) -> str:
    frames = list(payload.get("frames", ()))
    worst = sorted(frames, key=lambda f: -float(f["rms_px"]))[:WORST_FRAMES]
    out = ['<section id="frames"><h2>Frames</h2>', f"<h3>Worst {len(worst)} frames used</h3>"]
    out.append(_table([[_e(f.get("name") or f"frame {f['index']}"), f"#{int(f['index'])}", f"#{float(f['rms_px']):.3f}",
                        f"#{int(f['corners'])}"] for f in worst], header=("frame", "index", "RMS px", "corners")))
    dropped = list(payload.get("dropped_frames", ()))
    out.append(f"<h3>Frames dropped by the robust solve: {len(dropped)}</h3>")
    if dropped:
        out.append(_table([[f"#{int(d['frame_index'])}", _e(d["reason"])] for d in dropped], header=("frame", "why")))
    corners = sorted(payload.get("dropped_corners", ()), key=lambda d: -float(d["residual_px"]))
    out.append(f"<h3>Corners dropped as outliers: {len(corners)}</h3>")
    if corners:
        out.append(_table([[f"#{int(d['frame_index'])}", f"#{int(d['corner_id'])}", f"#{float(d['residual_px']):.2f}"]
                           for d in corners[:LISTED_CORNERS]], header=("frame", "corner id", "residual px")))
        if len(corners) > LISTED_CORNERS:
            out.append(f"<p class='small'>and {len(corners) - LISTED_CORNERS} more (all in calibration.json)</p>")
    rejections = {k: v for k, v in payload.get("coverage", {}).get("rejections", {}).items() if v and k != "accepted"}
    if rejections:
        out.append("<h3>Frames not taken during capture</h3>")
        out.append(_table([[_e(k), f"#{int(v)}"] for k, v in sorted(rejections.items(), key=lambda kv: -kv[1])],
                          header=("why", "frames")))
    return "".join(out) + "</section>"


def _pictures_section(pictures: Sequence[Path]) -> str:
    by_name = {Path(p).name: Path(p) for p in pictures}
    order = [n for n in PICTURE_CAPTIONS if n in by_name] + sorted(n for n in by_name if n not in PICTURE_CAPTIONS)
    out = ['<section id="pictures"><h2>Pictures</h2>']
    for name in order:
        heading, caption = PICTURE_CAPTIONS.get(name, (name, ""))
        data = base64.b64encode(by_name[name].read_bytes()).decode("ascii")
        out.append(f'<figure id="{_e(name.removesuffix(".png"))}"><h3>{_e(heading)}</h3>'
                   f'<img alt="{_e(heading)}" src="data:image/png;base64,{data}">'
                   f"<figcaption>{_e(caption)} <span class='small'>({_e(name)})</span></figcaption></figure>")
    return "".join(out) + "</section>"


def _provenance_section(payload: Mapping[str, Any]) -> str:
    command = shlex.join(str(a) for a in payload.get("command_line", ()))
    board = payload.get("board", {})
    src = payload.get("source", {})
    lens = payload.get("lens_state", {})
    rows = [
        ["calibcoach version", _e(payload.get("calibcoach_version", ""))],
        ["created", _e(payload.get("created", ""))],
        ["source", _e(src.get("description", ""))],
        ["frames read", f"{_e(src.get('frames_read', ''))} of {_e(src.get('frame_count') or 'unknown')} "
                        f"in {_f(src.get('replay_seconds'), 1)} s"],
        ["board", _e(", ".join(f"{k} {v}" for k, v in board.items()))],
    ]
    if lens:
        rows.append(["lens controls", _e(", ".join(f"{k} {v}" for k, v in lens.items()))])
    return (f'<section id="provenance"><h2>How it was made</h2><pre id="command">{_e(command)}</pre>'
            + _table(rows) + "</section>")
