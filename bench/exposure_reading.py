"""The exposure read off each cached render's edges and motion (coverage/exposure.py), against the truth.

Each render is replayed once with the defaults; every judged frame's edge widths and corner
velocities, as the session handed them to its `ExposureReader`, are kept, and the reading is
taken from them twice: as calibcoach takes it (the line refitted for the width measure's response
to a smear, `_RESPONSE_ROUNDS`) and as the plain line (no refit), so the two differ by nothing else.

    .venv/bin/python bench/exposure_reading.py [RENDER ...]   # default: every cached "smooth" render

Writes bench/results/exposure_reading.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))

from heldout import render_exposure_s  # noqa: E402  (bench/heldout.py)
from renders import CELLS, cached_renders, capture_path  # noqa: E402

import calibcoach.coverage.exposure as exposure  # noqa: E402
from calibcoach.app.replay import run_replay  # noqa: E402
from calibcoach.coverage.board import BoardSpec  # noqa: E402
from calibcoach.drivers.replay import open_source  # noqa: E402


def reader_of(name: str) -> exposure.ExposureReader:
    """The reader the replay of render `name` filled (the session's own, kept when it is made)."""
    made: list[exposure.ExposureReader] = []
    original = exposure.ExposureReader.__init__

    def keep(self: exposure.ExposureReader) -> None:
        original(self)
        made.append(self)

    exposure.ExposureReader.__init__ = keep  # type: ignore[method-assign]
    try:
        cell, seed = name.rsplit("_s", 1)
        run_replay(open_source(capture_path(cell, int(seed))), BoardSpec())
    finally:
        exposure.ExposureReader.__init__ = original  # type: ignore[method-assign]
    return made[-1]


def reading_s(reader: exposure.ExposureReader, interval_s: float, rounds: int) -> float:
    kept = exposure._RESPONSE_ROUNDS
    exposure._RESPONSE_ROUNDS = rounds
    try:
        value = reader.reading(interval_s).exposure_s
    finally:
        exposure._RESPONSE_ROUNDS = kept
    return float("nan") if value is None else value


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("renders", nargs="*")
    args = parser.parse_args()
    names = args.renders or [f"{c}_s{s}" for c, s in cached_renders() if c.startswith("smooth_")]
    lines = ["# The exposure read off the footage against the render's", "",
             "`bench/exposure_reading.py`: each render replayed with the defaults; the reading from the frames the "
             "session judged, with the width measure's response (as calibcoach reads it) and as the plain line.", "",
             "| render | truth, ms | read, ms | / truth | plain line, ms | / truth |", "|---|---|---|---|---|---|"]
    logs: dict[str, list[float]] = {"read": [], "plain": []}
    for name in names:
        interval = 1.0 / CELLS[name.rsplit("_s", 1)[0]].fps
        reader = reader_of(name)
        truth = render_exposure_s(name)
        read, plain = reading_s(reader, interval, exposure._RESPONSE_ROUNDS), reading_s(reader, interval, 0)
        for key, value in (("read", read), ("plain", plain)):
            if np.isfinite(value):
                logs[key].append(np.log(value / truth))
        lines.append(f"| {name} | {truth * 1e3:.1f} | {read * 1e3:.1f} | {read / truth:.2f} | {plain * 1e3:.1f} | {plain / truth:.2f} |")
        print(lines[-1], flush=True)
    lines += ["", "| reading | read on | RMS of the log error | mean | range (/ truth) |", "|---|---|---|---|---|"]
    for key, label in (("read", "with the response (calibcoach)"), ("plain", "plain line")):
        e = np.array(logs[key])
        lines.append(f"| {label} | {e.size} of {len(names)} | {np.sqrt(np.mean(e**2)):.3f} | {np.exp(np.mean(e)) - 1:+.1%} | "
                     f"{np.exp(e.min()):.2f}-{np.exp(e.max()):.2f} |")
    (ROOT / "results" / "exposure_reading.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines[-4:]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
