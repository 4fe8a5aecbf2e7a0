"""What smear within the exposure does to the corners: residuals after a pose fit, by the true smear.

Every frame of a render with >= 12 corners is detected (calibcoach's detector, every frame), its
pose fitted to its corners under the true lens (solvePnP, then Levenberg-Marquardt), and the RMS of
what is left is binned by the frame's true smear: its fastest corner's motion within the exposure,
from the true poses either side (bench/heldout.py `exposure_smear_px`). What a pose absorbs (the
board as it sat mid-exposure rather than at the frame's time) does not harm a calibration; what is
left after the fit does. The "smooth" cells of bench/renders.py render every smear over ~1 px;
the others render a smear under ~4 px as a sharp frame, so only the smooth ones answer the question.

    .venv/bin/python bench/smear_corners.py [--renders smooth_careful720_png_s101 ...] [--out smear_corners]

Without --renders: every smooth render in bench/cache. Writes bench/results/<out>.md and .json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))

from heldout import detect_all, exposure_smear_px, render_exposure_s  # noqa: E402  (bench/heldout.py)
from renders import CACHE, CELLS, cached_renders, capture_path  # noqa: E402

from calibcoach.coverage.board import BoardSpec  # noqa: E402
from calibcoach.drivers.recording import read_truth  # noqa: E402

BINS_PX = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, np.inf)
MIN_CORNERS = 12  # enough for the pose fit to leave the corners' own error


def residuals_by_smear(name: str) -> dict:
    cell, seed = name.rsplit("_s", 1)
    truth = read_truth(CACHE / name)
    camera = truth.camera
    exposure_s = render_exposure_s(name)
    smear = exposure_smear_px(truth, exposure_s, CELLS[cell].fps, BoardSpec())
    found, _seconds = detect_all(capture_path(cell, int(seed)))
    K, dist = camera.camera_matrix, camera.opencv_dist()
    smears, rms = [], []
    for index, detection in found.items():
        if detection.corner_count < MIN_CORNERS or index not in smear:
            continue
        board = detection.object_points_m.astype(np.float64)
        image = detection.corners_px.astype(np.float64)
        ok, rvec, tvec = cv2.solvePnP(board, image, K, dist)
        if not ok:
            continue
        rvec, tvec = cv2.solvePnPRefineLM(board, image, K, dist, rvec, tvec)
        left = image - camera.project(board, rvec.ravel(), tvec.ravel())
        smears.append(round(smear[index], 4))
        rms.append(round(float(np.sqrt(np.mean(np.sum(left**2, axis=1)))), 5))
    return {"exposure_ms": exposure_s * 1e3, "smear_px": smears, "residual_px": rms}


def _table(name: str, data: dict) -> list[str]:
    smears, rms = np.array(data["smear_px"]), np.array(data["residual_px"])
    still = float(np.median(rms[smears < BINS_PX[1]])) if np.any(smears < BINS_PX[1]) else float("nan")
    lines = [f"### {name} (exposure {data['exposure_ms']:.0f} ms)", "",
             "| true smear, px | frames | residual after the pose fit, px: median | p90 | median / still frames' |",
             "|---|---|---|---|---|"]
    for low, high in zip(BINS_PX[:-1], BINS_PX[1:], strict=True):
        chosen = (smears >= low) & (smears < high)
        if chosen.any():
            median = float(np.median(rms[chosen]))
            lines.append(f"| {low:g}-{high:g} | {int(chosen.sum())} | {median:.3f} | {np.percentile(rms[chosen], 90):.3f} | "
                         f"{median / still:.2f} |")
    return [*lines, ""]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--renders", nargs="+", help="e.g. smooth_dim720_mjpg_s101 (default: every cached smooth render)")
    parser.add_argument("--out", default="smear_corners")
    args = parser.parse_args()
    names = args.renders or [f"{cell}_s{seed}" for cell, seed in cached_renders() if cell.startswith("smooth")]
    results = {name: residuals_by_smear(name) for name in names}
    lines = ["# What smear within the exposure does to the corners", "",
             "`bench/smear_corners.py`: every frame with >= 12 corners, its pose fitted under the true lens; the RMS of the "
             "corners' residuals, binned by the frame's true smear (its fastest corner's motion within the exposure).", ""]
    for name, data in results.items():
        lines += _table(name, data)
    (ROOT / "results" / f"{args.out}.md").write_text("\n".join(lines) + "\n")
    (ROOT / "results" / f"{args.out}.json").write_text(json.dumps(results))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
