"""Smeared frames and the final solve: judged one frame at a time, or by the exposure read off the capture.

During a capture each frame is judged by its own edges (coverage/sharpness.py), which show a smear
of 2 px only faintly on a noisy frame. Since 2026-12-05 the final solve also leaves out every frame
whose fastest corner moved more than `SelectorSettings.max_solve_smear_px` within the exposure, the
exposure read off the whole capture's moving frames (coverage/exposure.py) and each frame's speed
measured across it from its neighbours. `--limit` sets that limit for the run (e.g. 1.5, the
selector's live limit).

For every render given (bench/renders.py; the "smooth" cells render every smear over ~1 px, the
others only those over ~4 px), `run_replay` + `finish` with the defaults, once without the final
solve's smear test and once with it; reported: the error against the lens truth over the covered
region (bench/accuracy.py's `score`), the frames in the final solve and how many of them smeared
more than the limit at their fastest corner by the truth, the exposure read against the render's,
and the frames the test left out.

    .venv/bin/python bench/smear_filter.py [--renders smooth_dim720_mjpg_s101 ...] [--out smear_filter]
    .venv/bin/python bench/smear_filter.py --merge bench/results/a.json bench/results/b.json --out smear_filter

Without --renders: every render in bench/cache. Writes bench/results/<out>.md and .json.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))

from heldout import cached_capture, exposure_smear_px, geometric_mean_interval, render_exposure_s, score_on  # noqa: E402  (bench/heldout.py)
from renders import CELLS, cached_renders  # noqa: E402

from calibcoach.app.replay import run_replay  # noqa: E402
from calibcoach.app.session_finish import SessionFinish  # noqa: E402
from calibcoach.coverage.board import BoardSpec  # noqa: E402
from calibcoach.coverage.select import SelectorSettings  # noqa: E402
from calibcoach.drivers.replay import open_source  # noqa: E402

VARIANTS = ("frame by frame", "exposure read off the capture")
LIMIT_PX = SelectorSettings().max_solve_smear_px  # the final solve's smear limit (`--limit` changes it)


@contextmanager
def variant(name: str) -> Iterator[None]:
    """The final solve's smear test off ("frame by frame") or as shipped, inside the block."""
    shipped = SessionFinish._leave_out_smeared

    def at_limit(self) -> None:
        self.settings = replace(self.settings, selector=replace(self.settings.selector, max_solve_smear_px=LIMIT_PX))
        shipped(self)

    SessionFinish._leave_out_smeared = (lambda self: None) if name == "frame by frame" else at_limit  # type: ignore[method-assign]
    try:
        yield
    finally:
        SessionFinish._leave_out_smeared = shipped  # type: ignore[method-assign]


def replays(name: str) -> dict[str, dict]:
    path, truth, yardstick = cached_capture(name)
    exposure_s = render_exposure_s(name)
    smear = exposure_smear_px(truth, exposure_s, CELLS[name.rsplit("_s", 1)[0]].fps, BoardSpec())
    rows: dict[str, dict] = {"truth": {"exposure_ms": exposure_s * 1e3}}
    for name_of_variant in VARIANTS:
        start = time.perf_counter()
        with variant(name_of_variant):
            session, _stats = run_replay(open_source(path), BoardSpec())
            result = session.finish()
        used = [v.frame_index for v in result.calibration.views]
        reading = session.exposure
        rows[name_of_variant] = {
            "error_px": score_on(truth.camera, result.calibration.camera, yardstick), "frames": len(used),
            "smeared": sum(smear.get(i, 0.0) > LIMIT_PX for i in used), "limit_px": LIMIT_PX, "verdict": result.verdict.grade,
            "left_out": session.smeared_left_out, "seconds": time.perf_counter() - start,
            "exposure_ms": None if reading is None or reading.exposure_s is None else reading.exposure_s * 1e3,
            "relative_error": None if reading is None else reading.relative_error,
            "informative": None if reading is None else reading.informative_frames,
        }
    return rows


def main() -> int:
    global LIMIT_PX
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--renders", nargs="+", help="e.g. smooth_dim720_mjpg_s101 (default: every cached render)")
    parser.add_argument("--out", default="smear_filter")
    parser.add_argument("--limit", type=float, default=SelectorSettings().max_solve_smear_px, help="the final solve's smear limit, px")
    parser.add_argument("--merge", nargs="+", type=Path, help="only summarise these earlier .json results together")
    args = parser.parse_args()
    LIMIT_PX = args.limit
    results: dict[str, dict] = {}
    if args.merge:
        for path in args.merge:
            results.update(json.loads(path.read_text()))
    else:
        for name in args.renders or [f"{cell}_s{seed}" for cell, seed in cached_renders()]:
            results[name] = replays(name)
            print(_row(name, results[name]), flush=True)
            (ROOT / "results" / f"{args.out}.json").write_text(json.dumps(results, indent=1))  # kept if a later one dies
    a, b = VARIANTS
    lines = ["# Smeared frames and the final solve: judged frame by frame, or by the exposure read off the capture", "",
             "`bench/smear_filter.py`: each render replayed both ways (`run_replay` + `finish`, defaults); error against "
             "the lens truth over the covered region; \"smeared\": frames of the final solve whose fastest corner moved "
             "more than the final solve's smear limit within the exposure by the truth; the exposure as read (its standard "
             "error, and the frames that showed it) against the render's.", "",
             f"| render | {a}: error, px | frames | smeared | {b}: error, px | frames | smeared | left out | "
             "exposure read, ms | true, ms | ratio |",
             "|---|---|---|---|---|---|---|---|---|---|---|", *(_row(name, rows) for name, rows in results.items())]
    lines += ["", "| cell | renders | error ratio, geometric mean [95% bootstrap interval] | better / same / worse |",
              "|---|---|---|---|"]
    cells = sorted({n.rsplit("_s", 1)[0] for n in results})
    groups = [*((c, [c]) for c in cells), ("smooth renders", [c for c in cells if c.startswith("smooth")]),
              ("every render", cells)]
    for label, chosen in groups:
        ratios = np.array([r[b]["error_px"] / r[a]["error_px"] for n, r in results.items() if n.rsplit("_s", 1)[0] in chosen])
        if ratios.size:
            lines.append(f"| {label} | {ratios.size} | {geometric_mean_interval(ratios)} | {int((ratios < 0.999).sum())} / "
                         f"{int((np.abs(ratios - 1) <= 0.001).sum())} / {int((ratios > 1.001).sum())} |")
    (ROOT / "results" / f"{args.out}.md").write_text("\n".join(lines) + "\n")
    (ROOT / "results" / f"{args.out}.json").write_text(json.dumps(results, indent=1))
    print("\n".join(lines[len(results) + 6:]))
    return 0


def _row(name: str, rows: dict) -> str:
    a, b = (rows[v] for v in VARIANTS)
    read = "unknown" if b["exposure_ms"] is None else f"{b['exposure_ms']:.1f}"
    error = b.get("relative_error")
    bound = "" if error is None else f" (+-{error:.0%}, {b.get('informative')} frames)"
    return (f"| {name} (limit {b.get('limit_px', 1.5):g} px) | {a['error_px']:.4f} ({a['verdict']}) | {a['frames']} | {a['smeared']} | {b['error_px']:.4f} "
            f"({b['verdict']}) | {b['frames']} | {b['smeared']} | {b['left_out']} | {read}{bound} | "
            f"{rows['truth']['exposure_ms']:.1f} | {b['error_px'] / a['error_px']:.2f} |")


if __name__ == "__main__":
    raise SystemExit(main())
