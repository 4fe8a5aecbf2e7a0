"""Rendered captures for the accuracy bench: PNG folders and MJPG videos with their lens truth.

A capture is rendered once into bench/cache/<cell>_s<seed>/ (git-ignored): `frames/` (PNG) or
`capture.avi` (MJPG), and `truth.json` (the lens and every frame's board pose). Each cell fixes
what a person and a room do to the footage (lens, hand style, tremor, light, container, frame
rate); the seed draws everything else, including the exposure time, so no constant can be fitted
to one exposure or one path.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector, Detection
from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.recording import write_truth
from calibcoach.drivers.replay import open_source
from calibcoach.drivers.sim import LENSES, SimulatedCamera, handheld_trajectory

CACHE = Path(__file__).resolve().parent / "cache"
# Webcam MJPG at its usual quality: 8x8-block artefacts of about one grey level on the board's edges.
MJPG_QUALITY = 80
# Office exposures of webcams run from 1/100 s (bright) to 1/30 s (auto-exposure at its frame-rate
# limit); each render draws one, so smear thresholds cannot ride on one simulator exposure.
EXPOSURE_RANGE_S = (0.008, 0.033)


def _wide1080() -> CameraModel:
    """A ~105 deg action-camera-like 1080p lens: the 115 deg wide720 profile, resized and zoomed 1.1x (104 deg across)."""
    base = LENSES["wide720"].resized((1920, 1080))
    K = base.camera_matrix.copy()
    K[0, 0] *= 1.1
    K[1, 1] *= 1.1
    return CameraModel("rational", K, base.dist_coeffs, (1920, 1080))


BENCH_LENSES: dict[str, CameraModel] = {**LENSES, "wide1080": _wide1080()}


@dataclass(frozen=True)
class Cell:
    """What is held fixed over the renders of one bench cell."""

    lens: str
    style: str  # "careful" | "sloppy" (fast swings, exits) | "frontal"
    tremor: float  # x the style's tremor: 1 steady, 4 shaky
    container: str  # "png" folder or "mjpg" video
    low_light: bool
    fps: float
    seconds: float
    # image motion between the sub-frames of a smear (drivers/sim.py): at the default 2 px a smear
    # under ~4 px renders sharp; the "smooth" cells render everything over ~1 px as a smear
    smear_step_px: float = 2.0

    @property
    def frames(self) -> int:
        return int(round(self.seconds * self.fps))


CELLS: dict[str, Cell] = {
    "careful720_png": Cell("webcam720", "careful", 1.0, "png", False, 30.0, 784 / 30),
    "shaky720_png": Cell("webcam720", "careful", 4.0, "png", False, 30.0, 784 / 30),
    "dim720_mjpg": Cell("webcam720", "careful", 2.0, "mjpg", True, 30.0, 784 / 30),
    "messy720_mjpg": Cell("webcam720", "sloppy", 1.0, "mjpg", False, 30.0, 784 / 30),
    "wide1080_mjpg": Cell("wide1080", "careful", 2.0, "mjpg", False, 20.0, 26.0),
    "fisheye150_png": Cell("fisheye150", "careful", 2.0, "png", False, 30.0, 784 / 30),
    # the same hands in the other container: the held-out judging reads each 720p style both as a
    # PNG folder (no timestamps: judged as photos, by the image alone) and as an MJPG video
    "careful720_mjpg": Cell("webcam720", "careful", 1.0, "mjpg", False, 30.0, 784 / 30),
    "dim720_png": Cell("webcam720", "careful", 2.0, "png", True, 30.0, 784 / 30),
    "messy720_png": Cell("webcam720", "sloppy", 1.0, "png", False, 30.0, 784 / 30),
    # The cells above render a smear under ~4 px (at the paper's corners) as a sharp frame, so the
    # smear a held board's tremor makes never shows in them; these render it (2026-12-05).
    "smooth_dim720_mjpg": Cell("webcam720", "careful", 2.0, "mjpg", True, 30.0, 784 / 30, smear_step_px=0.5),
    "smooth_careful720_png": Cell("webcam720", "careful", 1.0, "png", False, 30.0, 784 / 30, smear_step_px=0.5),
    "smooth_shaky720_png": Cell("webcam720", "careful", 4.0, "png", False, 30.0, 784 / 30, smear_step_px=0.5),
    # the other hands and lenses with the smear shown (2026-12-05, second session)
    "smooth_messy720_mjpg": Cell("webcam720", "sloppy", 1.0, "mjpg", False, 30.0, 784 / 30, smear_step_px=0.5),
    "smooth_wide1080_mjpg": Cell("wide1080", "careful", 2.0, "mjpg", False, 20.0, 26.0, smear_step_px=0.5),
    "smooth_fisheye150_png": Cell("fisheye150", "careful", 2.0, "png", False, 30.0, 784 / 30, smear_step_px=0.5),
    # the held-out judging's other containers of the 720p hands (2026-12-06): rendered with seeds
    # 106-110 (`HELD_OUT_SEEDS`), which no run or tuning had seen when they were added
    "smooth_careful720_mjpg": Cell("webcam720", "careful", 1.0, "mjpg", False, 30.0, 784 / 30, smear_step_px=0.5),
    "smooth_messy720_png": Cell("webcam720", "sloppy", 1.0, "png", False, 30.0, 784 / 30, smear_step_px=0.5),
    "smooth_dim720_png": Cell("webcam720", "careful", 2.0, "png", True, 30.0, 784 / 30, smear_step_px=0.5),
}
# Seeds no tuning of calibcoach has used (the unit tests, guided bench and recordings use 0-9).
SEEDS = (101, 102, 103, 104, 105)
# Seeds kept back for a check on footage nothing was looked at or changed against (first used 2026-12-06).
HELD_OUT_SEEDS = (106, 107, 108, 109, 110)
# A second such batch, for the capture styles the first one left out (first used 2026-12-06, 09:10):
# whether the held-frame scan's cost against `--every-frame` on the first batch was the scan or the draw.
HELD_OUT_SEEDS_2 = (111, 112, 113)
# A third, rendered after the verdict's missing-tilt factor was chosen on the seeds above (2026-12-06,
# second session; bench/missing_tilt_factor.py), for the fast-swinging hands that lack tilts.
HELD_OUT_SEEDS_3 = (114, 115, 116, 117, 118, 119)


def cached_renders() -> list[tuple[str, int]]:
    """(cell, seed) of every render already in bench/cache, sorted."""
    return sorted((cell, int(folder.name.rsplit("_s", 1)[1])) for cell in CELLS for folder in CACHE.glob(f"{cell}_s*")
                  if (folder / "truth.json").exists())


def capture_path(name: str, seed: int) -> Path:
    """The folder calibcoach reads: the PNG folder, or the .avi for video cells."""
    folder = CACHE / f"{name}_s{seed}"
    return folder / ("frames" if CELLS[name].container == "png" else "capture.avi")


def detected_frames(name: str, *, every: int, min_corners: int) -> Iterator[tuple[int, np.ndarray, Detection]]:
    """(index, grey, detection) of every `every`-th frame of cached render `name` (e.g.
    "dim720_png_s104") whose board shows at least `min_corners` corners, detected as the scan does."""
    folder = CACHE / name
    detector = CharucoBoardDetector(BoardSpec())
    with open_source(folder / "frames" if (folder / "frames").is_dir() else folder / "capture.avi") as source:
        for frame in source:
            if frame.index % every:
                continue
            grey = frame.grey()
            detection = detector.detect(grey)
            if detection.corner_count >= min_corners:
                yield frame.index, grey, detection


def render(name: str, seed: int) -> Path:
    """Render cell `name` with `seed` unless cached; returns the capture's folder (holds truth.json)."""
    cell = CELLS[name]
    folder = CACHE / f"{name}_s{seed}"
    if (folder / "truth.json").exists():
        return folder
    # Rendered into a folder of this process's own and renamed into place when whole: two benches
    # asking for the same render at once each render it but never write into one file (two did, and
    # the capture was lost), and a render cut short leaves nothing that looks cached.
    work = CACHE / f".{name}_s{seed}.{os.getpid()}.partial"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    camera, spec = BENCH_LENSES[cell.lens], BoardSpec()
    rng = np.random.default_rng([seed, 2026])
    exposure_s = float(rng.uniform(*EXPOSURE_RANGE_S))
    trajectory = handheld_trajectory(camera, spec, cell.style, seconds=cell.seconds, seed=seed, tremor_scale=cell.tremor)
    poses = trajectory.sample(seconds=cell.seconds, fps=cell.fps)
    source = SimulatedCamera(camera, spec, poses, seed=seed, lens_name=cell.lens, trajectory=trajectory,
                             low_light=cell.low_light, exposure_s=exposure_s, smear_step_px=cell.smear_step_px)
    start = time.perf_counter()
    writer = None
    if cell.container == "png":
        (work / "frames").mkdir(exist_ok=True)
    else:
        writer = cv2.VideoWriter(str(work / "capture.avi"), cv2.VideoWriter_fourcc(*"MJPG"), cell.fps, camera.image_size)
        writer.set(cv2.VIDEOWRITER_PROP_QUALITY, MJPG_QUALITY)
    for frame in source:
        image = frame.image if frame.image.ndim == 3 else cv2.cvtColor(frame.image, cv2.COLOR_GRAY2BGR)
        if writer is None:
            cv2.imwrite(str(work / "frames" / f"{frame.index:06d}.png"), frame.image)
        else:
            writer.write(image)
    if writer is not None:
        writer.release()
    write_truth(work, camera, [(p.index, p.rvec, p.tvec) for p in poses])
    (work / "exposure_s.txt").write_text(f"{exposure_s:.4f}\n")
    if not (folder / "truth.json").exists():  # else another process finished first: its render stands
        shutil.rmtree(folder, ignore_errors=True)  # a render cut short by the layout before this one
        os.rename(work, folder)
    shutil.rmtree(work, ignore_errors=True)
    print(f"rendered {folder.name}: {len(poses)} frames, exposure {exposure_s * 1e3:.0f} ms, "
          f"{time.perf_counter() - start:.0f} s", flush=True)
    return folder


if __name__ == "__main__":
    import sys

    # renders.py [--held-out | --held-out-2 | --held-out-3] [CELL ...]: every cell by default, the bench's seeds unless held out
    batches = {"--held-out": HELD_OUT_SEEDS, "--held-out-2": HELD_OUT_SEEDS_2, "--held-out-3": HELD_OUT_SEEDS_3}
    chosen = [batches[a] for a in sys.argv[1:] if a in batches]
    names = [a for a in sys.argv[1:] if a not in batches] or list(CELLS)
    for seed in chosen[0] if chosen else SEEDS:
        for cell_name in names:
            render(cell_name, seed)
