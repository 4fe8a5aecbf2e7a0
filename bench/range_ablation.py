"""What a missing range costs: each render replayed whole, then with its near (or far) views taken out.

The verdict asks for near and far views. This bench measures what leaving one range out does to
the calibration and to E, on captures that did show both: after the replay (`run_replay`) and
before the final solve, every kept, reserve and repeat view whose board centre lies in the dropped
range (by the true pose and the true lens's ranges, so the bench's choice does not depend on the
solve it judges) is removed. Reported per render and drop: views left, what the final coverage
misses, E over the covered region and over the whole image, the true error over the capture's
covered region and over the whole image, the verdict, and the true error over E (honest near 1).

    .venv/bin/python bench/range_ablation.py [careful720_png_s101 ...]   # default: all of bench/cache

Writes bench/results/range_ablation.md. Renders are not made here (bench/renders.py does that).
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))

from accuracy import score, whole_image_error  # noqa: E402  (bench/accuracy.py)
from heldout import detect_all  # noqa: E402
from renders import CACHE, capture_path  # noqa: E402

from calibcoach.app.replay import run_replay  # noqa: E402
from calibcoach.coverage.board import BoardSpec  # noqa: E402
from calibcoach.coverage.candidates import ranges_for  # noqa: E402
from calibcoach.drivers.recording import read_truth  # noqa: E402
from calibcoach.drivers.replay import open_source  # noqa: E402

HEADER = ("| render | dropped | views | missing | E covered | E whole image | true error covered | true error whole image "
          "| true / E | verdict |\n|---|---|---|---|---|---|---|---|---|---|")


def true_range_cells(truth, session) -> dict[int, str]:
    """frame index -> 'near' / 'mid' / 'far' of its true board centre under the true lens's ranges."""
    ranges = ranges_for(truth.camera, session.geometry)
    cells = {}
    for index, rvec, tvec in truth.poses:
        rotation, _ = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))
        centre = rotation @ session.geometry.centre_m + np.asarray(tvec, np.float64).ravel()
        cells[int(index)] = ranges.cell(float(np.linalg.norm(centre)))
    return cells


def drop_range(session, cells: dict[int, str], dropped: str) -> None:
    """Take every view whose board centre is in range `dropped` out of what the final solve is offered."""
    def keep(view) -> bool:
        return cells.get(view.frame_index) != dropped
    session.views = [v for v in session.views if keep(v)]
    session._reserve = [(v, q) for v, q in session._reserve if keep(v)]
    session._repeats = [v for v in session._repeats if keep(v)]


def rows(name: str) -> list[str]:
    cell, seed = name.rsplit("_s", 1)
    path = capture_path(cell, int(seed))
    truth = read_truth(CACHE / name)
    detections, _seconds = detect_all(path)
    yardstick = [d.corners_px for _i, d in sorted(detections.items()) if d.corner_count >= 6]
    made = []
    for dropped in ("-", "near", "far"):
        session, _stats = run_replay(open_source(path), BoardSpec())
        if dropped != "-":
            drop_range(session, true_range_cells(truth, session), dropped)
        try:
            result = session.finish()
        except Exception as exc:  # noqa: BLE001 - a bench row says what went wrong
            made.append(f"| {name} | {dropped} | - | failed: {str(exc)[:60]} | | | | | | |")
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


PREAMBLE = "# What a missing range costs\n\n`bench/range_ablation.py` (E in px, errors in px against the lens truth).\n\n"


def main() -> None:
    names = sys.argv[1:] or sorted(p.name for p in CACHE.iterdir() if (p / "truth.json").exists())
    made = [r for name in names for r in rows(name)]
    out = ROOT / "results" / "range_ablation.md"
    # what was written before: the text above the table, its rows, the reading below it; the rows of
    # renders not rerun here are kept (renders come and go from bench/cache)
    before, _, rest = (out.read_text() if out.exists() else PREAMBLE).partition(HEADER + "\n")
    old_rows, _, reading = rest.partition("\n\n")
    kept = [line for line in old_rows.splitlines() if line.startswith("| ") and line.split(" | ")[0][2:] not in names]
    table = sorted(kept + made, key=lambda line: (line.split(" | ")[0], ("-", "near", "far").index(line.split(" | ")[1])))
    out.write_text(before + HEADER + "\n" + "\n".join(table) + "\n" + ("\n" + reading if reading else ""))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
