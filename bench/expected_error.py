"""How well E predicts the true error: the model's E, the holds' scatter's, and the larger (reported).

For every cached render (bench/renders.py), `calibcoach calibrate`'s replay and final solve with
the defaults; its error against the lens truth over the covered region (bench/heldout.py's
yardstick), the expected error E from the model covariance and from the jackknife over holds
(app/solve/hold_jackknife.py), and the verdict. An honest E gives true / E an RMS of ~1 over many
captures (one capture's ratio scatters: its error is one draw); above 1 E understates.

    .venv/bin/python bench/expected_error.py [RENDER ...]   # e.g. smooth_dim720_mjpg_s105; default: all cached
    .venv/bin/python bench/expected_error.py --every-frame --out expected_error_every_frame

Writes bench/results/expected_error.md and .json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))

from accuracy import score  # noqa: E402  (bench/accuracy.py)
from heldout import cached_capture  # noqa: E402
from renders import cached_renders  # noqa: E402

from calibcoach.app.replay import run_replay  # noqa: E402
from calibcoach.coverage.board import BoardSpec  # noqa: E402
from calibcoach.drivers.replay import open_source  # noqa: E402

RESULTS = ROOT / "results"


def measure(name: str, every_frame: bool = False) -> dict:
    path, truth, yardstick = cached_capture(name)
    session, _stats = run_replay(open_source(path), BoardSpec(), every_frame=every_frame)
    result = session.finish()
    sources = result.expected_errors
    return {
        "render": name,
        "error_px": score(truth.camera, result.calibration.camera, yardstick),
        "model_px": sources.from_model_px,
        "between_holds_px": sources.between_holds_px,
        "holds": sources.holds,
        "reported_px": result.uncertainty.expected_error_px,
        "grade": result.verdict.grade,
        "trusted": result.verdict.trusted,
    }


def summary(rows: list[dict]) -> str:
    lines = ["# How well E predicts the true error", "",
             "`bench/expected_error.py`: each cached render replayed with the defaults; true error over the covered "
             "region against E from the model covariance, from the scatter between holds (jackknife, "
             "app/solve/hold_jackknife.py) and the larger, which is reported. Honest: RMS of true / E ~1.", "",
             "| render | true error, px | E model | E between holds (holds) | E reported | true / reported | verdict |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['render']} | {r['error_px']:.3f} | {r['model_px']:.3f} | {r['between_holds_px']:.3f} ({r['holds']}) | "
                     f"{r['reported_px']:.3f} | {r['error_px'] / r['reported_px']:.2f} | {r['grade']}{'' if r['trusted'] else ' (refused)'} |")
    lines += ["", "| renders | n | E | RMS of true / E | worst | understated > 1.5x | E > 0.2 px (refused at 720p) | true > 0.2 px |",
              "|---|---|---|---|---|---|---|---|"]
    groups = {"smooth-smear cells": [r for r in rows if r["render"].startswith("smooth_")],
              "older cells": [r for r in rows if not r["render"].startswith("smooth_")], "all": rows}
    for label, group in groups.items():
        if not group:
            continue
        err = np.array([r["error_px"] for r in group])
        for which, key in (("model", "model_px"), ("between holds", "between_holds_px"), ("reported (larger)", "reported_px")):
            e = np.array([r[key] if np.isfinite(r[key]) else r["model_px"] for r in group])
            q = err / e
            lines.append(f"| {label} | {len(group)} | {which} | {np.sqrt(np.mean(q**2)):.2f} | {q.max():.2f} | "
                         f"{int(np.sum(q > 1.5))} | {int(np.sum(e > 0.2))} | {int(np.sum(err > 0.2))} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("renders", nargs="*", help="cached render names (default: every cached render)")
    parser.add_argument("--out", default="expected_error")
    parser.add_argument("--every-frame", action="store_true", help="detect every frame in full (the scan's reference)")
    args = parser.parse_args()
    names = args.renders or [f"{cell}_s{seed}" for cell, seed in cached_renders()]
    rows = []
    for name in names:
        rows.append(measure(name, args.every_frame))
        r = rows[-1]
        print(f"{name}: true {r['error_px']:.3f}, E model {r['model_px']:.3f}, between holds {r['between_holds_px']:.3f} "
              f"({r['holds']}), {r['grade']}", flush=True)
    (RESULTS / f"{args.out}.json").write_text(json.dumps(rows, indent=1) + "\n")
    (RESULTS / f"{args.out}.md").write_text(summary(rows))
    print(summary(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
