"""How low E reads without a tilt, from bench/results/coverage_ablation.md, and what the verdict's factor trusts.

The verdict judges a capture that never showed some tilt on E (over the covered region and over the
whole image) times `verdict.MISSING_TILT_E_FACTOR`. This reads every row of the ablation table whose
final coverage lacks a tilt (as captured, or with the views of a tilt or range taken out) and reports:

- over the rows whose E over the whole image is within the trust bound (where the factor decides),
  the true error over E, worst and median, over the whole image and over the covered region;
- the rows the factor trusts, their worst true error, and the rows it refuses that were within
  0.05 px (what the factor costs);
- the same for the renders made after the factor was chosen (seed >= `FIRST_UNSEEN_SEED`), apart.

    .venv/bin/python bench/missing_tilt_factor.py

Writes bench/results/missing_tilt_factor.md. Nothing is replayed here: run coverage_ablation.py first.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))

from renders import HELD_OUT_SEEDS_3  # noqa: E402

from calibcoach.app.solve.verdict import ERROR_TRUST_PX, MISSING_TILT_E_FACTOR  # noqa: E402

TABLE = ROOT / "results" / "coverage_ablation.md"
# The factor was chosen (2026-12-06) on the renders with seeds 101-113; the third held-out batch
# was rendered afterwards, to check it on footage it was not chosen on.
FIRST_UNSEEN_SEED = min(HELD_OUT_SEEDS_3)
GOOD_ENOUGH_PX = 0.05  # the accuracy the judging asks of a 720p capture


@dataclass(frozen=True)
class Row:
    render: str
    dropped: str
    missing: str
    E_covered: float
    E_whole: float
    true_covered: float
    true_whole: float

    @property
    def seed(self) -> int:
        return int(self.render.rsplit("_s", 1)[1])

    def trusted(self, factor: float) -> bool:
        """The verdict's trust test for a capture lacking a tilt (720p, corner noise below the bound)."""
        return factor * self.E_whole <= ERROR_TRUST_PX and factor * self.E_covered <= ERROR_TRUST_PX


def tilt_missing_rows(text: str) -> list[Row]:
    """The table's rows whose final coverage lacks a tilt (failed rows skipped; a drop that took
    nothing out, such as "near" from a capture never held near, counted once)."""
    out: list[Row] = []
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 10 or cells[0] == "render" or " tilts" not in cells[3]:
            continue
        try:
            numbers = [float(c) for c in cells[4:8]]
        except ValueError:
            continue
        row = Row(cells[0], cells[1], cells[3], *numbers)
        if not any(r.render == row.render and (r.E_covered, r.E_whole, r.true_covered) == (row.E_covered, row.E_whole, row.true_covered)
                   for r in out):
            out.append(row)
    return out


def summary(rows: list[Row], factor: float) -> list[str]:
    decided = [r for r in rows if r.E_whole <= ERROR_TRUST_PX]
    if not decided:
        return ["(no rows)"]
    whole = np.array([r.true_whole / r.E_whole for r in decided])
    covered = np.array([r.true_covered / r.E_covered for r in decided])
    worst = decided[int(np.argmax(whole))]
    trusted = [r for r in rows if r.trusted(factor)]
    lost = [r for r in rows if not r.trusted(factor) and r.true_covered <= GOOD_ENOUGH_PX]
    let_in = [r for r in trusted if r.true_covered > GOOD_ENOUGH_PX]
    lines = [
        f"- rows lacking a tilt: {len(rows)}; with E over the whole image within {ERROR_TRUST_PX} px: {len(decided)}",
        f"- true / E over the whole image: median {np.median(whole):.2f}, worst {whole.max():.2f} "
        f"({worst.render}, {worst.dropped}: {worst.true_whole:.4f} px against E {worst.E_whole:.3f})",
        f"- true / E over the covered region: median {np.median(covered):.2f}, worst {covered.max():.2f}",
        f"- trusted at {factor:g}x: {len(trusted)}, true error over the covered region at most "
        + (f"{max(r.true_covered for r in trusted):.4f} px" if trusted else "-")
        + f"; of them over {GOOD_ENOUGH_PX} px: {len(let_in)}"
        + "".join(f" ({r.render} {r.dropped} {r.true_covered:.4f})" for r in let_in),
        f"- refused at {factor:g}x though within {GOOD_ENOUGH_PX} px: {len(lost)} of "
        f"{sum(r.true_covered <= GOOD_ENOUGH_PX for r in rows)}",
    ]
    return lines


def as_captured(rows: list[Row], factor: float) -> list[str]:
    """One line per render as captured (no views taken out): what the verdict now says of it."""
    table = ["| render | missing | E covered | E whole image | true error covered | trusted |", "|---|---|---|---|---|---|"]
    for r in rows:
        if r.dropped == "-":
            table.append(f"| {r.render} | {r.missing} | {r.E_covered:.3f} | {r.E_whole:.3f} | {r.true_covered:.4f} | "
                         f"{'yes' if r.trusted(factor) else 'no'} |")
    return table


def main() -> None:
    rows = tilt_missing_rows(TABLE.read_text())
    chosen_on = [r for r in rows if r.seed < FIRST_UNSEEN_SEED]
    unseen = [r for r in rows if r.seed >= FIRST_UNSEEN_SEED]
    factor = MISSING_TILT_E_FACTOR
    text = [
        "# How low E reads without a tilt",
        "",
        f"`bench/missing_tilt_factor.py` over `coverage_ablation.md` (px; the verdict's factor {factor:g}, "
        f"trust bound {ERROR_TRUST_PX} px at 720p).",
        "",
        f"## The renders the factor was chosen on (seeds below {FIRST_UNSEEN_SEED})",
        "",
        *summary(chosen_on, factor),
        "",
        f"## Renders made after it was chosen (seeds {FIRST_UNSEEN_SEED} and up)",
        "",
        *summary(unseen, factor),
        "",
        *as_captured(unseen, factor),
        "",
    ]
    out = ROOT / "results" / "missing_tilt_factor.md"
    out.write_text("\n".join(text))
    print("\n".join(text))


if __name__ == "__main__":
    main()
