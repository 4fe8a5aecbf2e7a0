"""The residual-pattern test (app/solve/residual_structure.py) where the answer is known: no pattern.

Every render is drawn with a flat board exactly as its spec says and a lens of the model family
calibcoach solves for, so a pattern fixed to the board or to the image can only be a false alarm.
For each render (bench/renders.py: by default every render already in bench/cache, or the
--cells x --seeds given, rendered on demand) the replay's final solve is tested
and its ratios (the fixed part's variance over what noise explains: ~1 for noise, flagged at
`FIXED_RATIO` and `FIXED_PX`) are listed with the median and worst per measure. The real board
that is off its spec is in bench/real_captures.py.

    .venv/bin/python bench/residual_patterns.py [--cells careful720_png dim720_mjpg ... --seeds 101 102 ...]

Writes bench/results/residual_patterns.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))
from renders import CELLS, cached_renders, capture_path, render  # noqa: E402  (bench/renders.py)

from calibcoach.app.replay import run_replay  # noqa: E402
from calibcoach.app.solve.residual_structure import FIXED_PX, FIXED_RATIO  # noqa: E402
from calibcoach.coverage.board import BoardSpec  # noqa: E402
from calibcoach.drivers.replay import open_source  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", nargs="+", choices=sorted(CELLS))
    parser.add_argument("--seeds", nargs="+", type=int)
    args = parser.parse_args()
    if args.cells or args.seeds:
        todo = [(cell, seed) for cell in args.cells or sorted(CELLS) for seed in args.seeds or [101]]
    else:
        todo = cached_renders()
    rows = ["| render | poses | board: corners judged | ratio | fixed px | image: cells judged | ratio | fixed px | flagged |",
            "|---|---|---|---|---|---|---|---|---|"]
    board_ratios, image_ratios, flagged = [], [], 0
    for cell, seed in todo:
        render(cell, seed)
        start = time.perf_counter()
        session, _stats = run_replay(open_source(capture_path(cell, seed)), BoardSpec())
        result = session.finish()
        s = result.residual_structure
        assert s is not None
        poses = len(set(session._look_alike_groups(result.calibration.views, result.calibration.camera)))
        hit = [name for name, p in (("board", s.board), ("image", s.image)) if p.flagged]
        flagged += bool(hit)
        if s.board.judged:
            board_ratios.append(s.board.ratio)
        if s.image.judged:
            image_ratios.append(s.image.ratio)
        rows.append(f"| {cell} s{seed} | {poses} | {s.board.places} | {s.board.ratio:.2f} | {s.board.rms_px:.4f} | "
                    f"{s.image.places} | {s.image.ratio:.2f} | {s.image.rms_px:.4f} | {', '.join(hit) or 'no'} |")
        print(rows[-1], f"({time.perf_counter() - start:.0f} s)", flush=True)
    text = "\n".join([
        f"# Residual patterns on renders (flat boards, fitting lenses): flagged at ratio >= {FIXED_RATIO} and >= {FIXED_PX} px",
        "", *rows, "",
        f"Board ratio: median {np.median(board_ratios):.2f}, worst {max(board_ratios):.2f} over {len(board_ratios)} judged; "
        f"image ratio: median {np.median(image_ratios):.2f}, worst {max(image_ratios):.2f} over {len(image_ratios)} judged; "
        f"{flagged} of {len(rows) - 2} renders flagged.",
    ])
    (ROOT / "results" / "residual_patterns.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
