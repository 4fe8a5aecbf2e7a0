"""When short coverage is trusted: E over the whole image against the truth over the whole image.

The verdict (app/solve/verdict.py) trusts a capture whose coverage is short of 85% when every tilt
was shown (only image regions or a range are missing: bench/coverage_ablation.py for the range) and
E over the whole image a board can be seen in -- the model's extrapolation into what is missing --
is within the trust bound. This bench shows, for each render already in bench/cache (or those
named), what that rule sees and what the truth says: coverage and what is missing, E over the
covered region and over the whole image, and the true error over each.

    .venv/bin/python bench/coverage_trust.py [messy720_mjpg_s101 ...]

Writes bench/results/coverage_trust.md (the rows of renders not rerun are kept). Renders are not made here (bench/renders.py does that).
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))

from accuracy import score, whole_image_error  # noqa: E402  (bench/accuracy.py)
from heldout import cached_capture  # noqa: E402
from renders import cached_renders  # noqa: E402
from results_table import write_merged  # noqa: E402

from calibcoach.app.replay import run_replay  # noqa: E402
from calibcoach.coverage.board import BoardSpec  # noqa: E402
from calibcoach.drivers.replay import open_source  # noqa: E402

PREAMBLE = ("# Short coverage, E over the whole image, and the truth\n\n`bench/coverage_trust.py` on the renders in "
            "bench/cache (E in px, errors in px against the lens truth).\n\n")
HEADER = ("| render | coverage | missing | E covered | E whole image | true error covered | true error whole image | verdict |\n"
          "|---|---|---|---|---|---|---|---|")


def row(name: str) -> str:
    path, recorded, yardstick = cached_capture(name)
    truth = recorded.camera
    session, _stats = run_replay(open_source(path), BoardSpec())
    result = session.finish()
    u, cov = result.uncertainty, result.coverage
    whole_E = result.reachable_error_px
    missing = cov.summary()["missing"]
    words = ", ".join(f"{len(v)} {k}" for k, v in missing.items() if v) or "-"  # type: ignore[union-attr]
    return (f"| {name} | {cov.completeness() * 100:.0f}% | {words} | {u.expected_error_px:.3f} | {whole_E:.3f} | "
            f"{score(truth, result.calibration.camera, yardstick):.4f} | {whole_image_error(truth, result.calibration.camera):.4f} | "
            f"{result.verdict.grade} |")


def main() -> None:
    names = sys.argv[1:] or [f"{cell}_s{seed}" for cell, seed in cached_renders()]
    rows = []
    for name in names:
        rows.append(row(name))
        print(rows[-1], flush=True)
    out = ROOT / "results" / "coverage_trust.md"
    write_merged(out, PREAMBLE, HEADER, rows, key=lambda line: (line.split(" | ")[0],))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
