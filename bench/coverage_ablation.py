"""What a missing range or tilt costs: each render replayed whole, then with one kind of view taken out.

The verdict asks for near and far views and every tilt (coverage/grid.py). This bench measures what
leaving one of them out does to the calibration and to E, on captures that did show it: after the
replay (`run_replay`) and before the final solve, every kept, reserve and repeat view that counts
for the dropped cell -- a range ("near", "far") or a tilt cell ("steep_x", "bottom_away", ...) --
is removed, judged by the true pose and the true lens's ranges, so the bench's choice does not
depend on the solve it judges. Reported per render and drop: views left, what the final coverage
misses, E over the covered region and over the whole image, the true error over the capture's
covered region and over the whole image, the verdict, and the true error over E (honest near 1).

    .venv/bin/python bench/coverage_ablation.py [--drop near far steep_x ...] [careful720_png_s101 ...]

Default: near and far, every render in bench/cache; `--drop` with nothing after it (renders named
before it) replays the captures as they are. Writes bench/results/coverage_ablation.md (the
rows of renders and drops not rerun are kept). Renders are not made here (bench/renders.py does that).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))

from accuracy import score, whole_image_error  # noqa: E402  (bench/accuracy.py)
from heldout import cached_capture  # noqa: E402
from renders import cached_renders  # noqa: E402
from results_table import write_merged  # noqa: E402

from calibcoach.app.replay import run_replay  # noqa: E402
from calibcoach.coverage.board import BoardSpec  # noqa: E402
from calibcoach.coverage.candidates import ranges_for  # noqa: E402
from calibcoach.coverage.grid import tilt_cells  # noqa: E402
from calibcoach.drivers.geometry import tilt_against_sight_deg  # noqa: E402
from calibcoach.drivers.replay import open_source  # noqa: E402

HEADER = ("| render | dropped | views | missing | E covered | E whole image | true error covered | true error whole image "
          "| true / E | verdict |\n|---|---|---|---|---|---|---|---|---|---|")


def true_cells(truth, session) -> dict[int, set[str]]:
    """frame index -> the range cell and tilt cells its true pose counts for, under the true lens's ranges."""
    ranges = ranges_for(truth.camera, session.geometry)
    cells = {}
    for index, rvec, tvec in truth.poses:
        rotation, _ = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))
        centre = rotation @ session.geometry.centre_m + np.asarray(tvec, np.float64).ravel()
        tilt, tilt_x, tilt_y = tilt_against_sight_deg(rotation[:, 2], centre)
        cells[int(index)] = {ranges.cell(float(np.linalg.norm(centre))), *tilt_cells(tilt, tilt_x, tilt_y)}
    return cells


def drop_views(session, cells: dict[int, set[str]], dropped: str) -> None:
    """Take every view that counts for cell `dropped` out of what the final solve is offered."""
    def keep(view) -> bool:
        return dropped not in cells.get(view.frame_index, set())
    session.views = [v for v in session.views if keep(v)]
    session._reserve = [(v, q) for v, q in session._reserve if keep(v)]
    session._repeats = [v for v in session._repeats if keep(v)]


def rows(name: str, drops: list[str]) -> list[str]:
    path, truth, yardstick = cached_capture(name)
    made = []
    for dropped in ["-", *drops]:
        session, _stats = run_replay(open_source(path), BoardSpec())
        if dropped != "-":
            drop_views(session, true_cells(truth, session), dropped)
        try:
            result = session.finish()
        except Exception as exc:  # noqa: BLE001 - a bench row says what went wrong
            made.append(f"| {name} | {dropped} | - | failed: {str(exc)[:60]} | | | | | | |")
            print(made[-1], flush=True)
            continue
        u, cov = result.uncertainty, result.coverage
        missing = cov.summary()["missing"]
        words = ", ".join(f"{len(v) if k == 'regions' else ' '.join(v)} {k}" for k, v in missing.items() if v) or "-"  # type: ignore[union-attr]
        error = score(truth.camera, result.calibration.camera, yardstick)
        made.append(f"| {name} | {dropped} | {len(result.calibration.views)} | {words} | {u.expected_error_px:.3f} | "
                    f"{result.reachable_error_px:.3f} | {error:.4f} | {whole_image_error(truth.camera, result.calibration.camera):.4f} | "
                    f"{error / u.expected_error_px:.2f} | {result.verdict.grade} |")
        print(made[-1], flush=True)
    return made


PREAMBLE = "# What a missing range or tilt costs\n\n`bench/coverage_ablation.py` (E in px, errors in px against the lens truth).\n\n"


def _order(line: str) -> tuple[str, int, str]:
    render, dropped = line.split(" | ")[0], line.split(" | ")[1]
    return render, ("-", "near", "far").index(dropped) if dropped in ("-", "near", "far") else 3, dropped


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--drop", nargs="*", default=["near", "far"],
                        help="cells whose views are taken out, one at a time (none: the captures as they are)")
    parser.add_argument("renders", nargs="*", help="cached renders (default: all of bench/cache)")
    args = parser.parse_args()
    names = args.renders or [f"{cell}_s{seed}" for cell, seed in cached_renders()]
    made = [r for name in names for r in rows(name, args.drop)]
    out = ROOT / "results" / "coverage_ablation.md"
    write_merged(out, PREAMBLE, HEADER, made, key=_order)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
