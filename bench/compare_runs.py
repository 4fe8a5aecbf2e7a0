"""Two runs of bench/expected_error.py over the same renders, paired: per cell and over all.

A render's truth error is one draw (which of a hold's frames reach the solve moves it by as much
as E says it may), so two ways of reading the same footage are compared by the geometric mean of
their error ratio over many renders, with a 95% bootstrap interval, never render by render.

    .venv/bin/python bench/compare_runs.py bench/results/expected_error_neighbour_motion.json \
        bench/results/expected_error_every_frame.json

Prints a markdown table: per cell the median and worst of each run and the geometric mean of
first / second (below 1: the first run is better).
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np


def errors(path: Path) -> dict[str, float]:
    return {row["render"]: float(row["error_px"]) for row in json.loads(path.read_text())}


def geometric_mean_interval(ratios: np.ndarray, draws: int = 5000) -> tuple[float, float, float]:
    logs = np.log(ratios)
    rng = np.random.default_rng(0)
    means = np.array([rng.choice(logs, logs.size).mean() for _ in range(draws)])
    low, high = np.percentile(means, [2.5, 97.5])
    return float(np.exp(logs.mean())), float(np.exp(low)), float(np.exp(high))


def table(first: dict[str, float], second: dict[str, float], labels: tuple[str, str]) -> str:
    shared = sorted(set(first) & set(second))
    cells: dict[str, list[str]] = {}
    for name in shared:
        cells.setdefault(re.sub(r"_s\d+$", "", name), []).append(name)
    lines = [f"| cell | renders | {labels[0]}: median / worst, px | {labels[1]}: median / worst, px | "
             f"{labels[0]} / {labels[1]}: geometric mean [95%] | better |", "|---|---|---|---|---|---|"]
    groups = [(cell, names) for cell, names in cells.items()]
    groups += [("smooth-smear 720p cells", [n for n in shared if n.startswith("smooth_") and "720" in n]),
               ("all", shared)]
    for cell, names in groups:
        a = np.array([first[n] for n in names])
        b = np.array([second[n] for n in names])
        mean, low, high = geometric_mean_interval(a / b)
        interval = f"[{low:.2f}, {high:.2f}]" if len(names) > 2 else ""
        lines.append(f"| {cell} | {len(names)} | {np.median(a):.4f} / {a.max():.4f} | {np.median(b):.4f} / {b.max():.4f} | "
                     f"{mean:.2f} {interval} | {int(np.sum(a < b))} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("first", type=Path)
    parser.add_argument("second", type=Path)
    parser.add_argument("--labels", nargs=2, default=("first", "second"))
    args = parser.parse_args()
    print(table(errors(args.first), errors(args.second), tuple(args.labels)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
