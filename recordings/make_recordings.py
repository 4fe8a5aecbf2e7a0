"""Regenerate the bundled simulated recordings (the README demo and the replay-test captures).

Each recording is a folder in calibcoach's recording format (docs/recording-format.md) written by
`RecordingWriter`, plus `truth.json` (the true lens and every true board pose, `write_truth`) and a
short README.md. Everything derives from fixed seeds, so a rerun with the same numpy and OpenCV
versions reproduces the same pixels.

Size: the folder is kept in git, so all recordings together must stay below ~40 MB. Frames are
grey and re-encoded at PNG compression 9 (the writer uses level 1 to keep up with a live camera).
Sensor noise is what costs the bytes (1 DN of iid noise is ~2 bits per pixel, ~230 KB per 720p
frame, whatever the compressor), so the recordings use a lighter noise than the live simulator's
default and a lower frame rate instead of a shorter capture; see recordings/README.md.

Usage:
    .venv/bin/python recordings/make_recordings.py --out recordings            # all of them
    .venv/bin/python recordings/make_recordings.py --out recordings --only frontal_webcam720
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2

from calibcoach.coverage.board import BoardSpec
from calibcoach.drivers.recording import RecordingWriter, write_truth
from calibcoach.drivers.sim import LENSES, SimulatedCamera, handheld_trajectory

_PNG_SMALLEST = [cv2.IMWRITE_PNG_COMPRESSION, 9, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_FILTERED]
BUDGET_MB = 55.0


@dataclass(frozen=True, slots=True)
class Recipe:
    """One bundled recording: which lens, which hand, how long."""

    name: str  # folder name under --out
    lens: str  # key of LENSES
    style: str  # "careful" | "sloppy" | "frontal"
    seconds: float
    fps: float
    seed: int  # path and noise seed
    purpose: str  # one line for the README


# ~265 KB per frame at 0.5 DN noise: ~185 frames fill ~50 MB of the 55 MB budget. The frame rates
# are low so that the captures keep their length (the careful path needs ~30 s to visit every
# target: quadrants, image corners, steep tilts, near and far); the fisheye's 3 fps buys it 15 s.
RECIPES = (
    Recipe("demo_webcam720_careful", "webcam720", "careful", 30.0, 4.0, 1,
           "the README demo: a careful capture that covers the image and calibrates well"),
    Recipe("frontal_webcam720", "webcam720", "frontal", 4.0, 5.0, 2,
           "a careless frontal-only capture: a low RMS, yet the lens is badly wrong at the image edges"),
    Recipe("fisheye150_careful", "fisheye150", "careful", 15.0, 3.0, 3,
           "a careful capture through a 150 deg Kannala-Brandt fisheye"),
)
NOISE_SIGMA_DN = 0.5  # recordings only; the live SimulatedCamera defaults to 1.5 DN
BLUR_SIGMA_PX = 0.6


def folder_size_mb(folder: Path) -> float:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) / 2**20


def make_recording(recipe: Recipe, out: Path, spec: BoardSpec) -> tuple[int, float]:
    """Render one recipe into out/recipe.name (replacing it); returns (frames, size in MB)."""
    folder = out / recipe.name
    if folder.exists():
        shutil.rmtree(folder)  # the writer refuses to overwrite a recording, by design
    camera = LENSES[recipe.lens]
    trajectory = handheld_trajectory(camera, spec, recipe.style, seconds=recipe.seconds, seed=recipe.seed)
    poses = trajectory.sample(seconds=recipe.seconds, fps=recipe.fps)
    source = SimulatedCamera(camera, spec, poses, noise_sigma=NOISE_SIGMA_DN, blur_sigma=BLUR_SIGMA_PX,
                             seed=recipe.seed, lens_name=recipe.lens, trajectory=trajectory)
    info = source.info
    with source, RecordingWriter(folder, camera_id=info.camera_id, kind=info.kind, image_size=info.image_size,
                                 fps=info.fps, controls=info.controls, board=info.board) as writer:
        for frame in source:
            writer.write(frame)
    for png in sorted((folder / "frames").glob("*.png")):
        _recompress(png)
    write_truth(folder, camera, source.truth.pose_tuples())
    (folder / "README.md").write_text(_readme(recipe, spec, len(poses), camera.image_size), encoding="utf-8")
    return len(poses), folder_size_mb(folder)


def _recompress(png: Path) -> None:
    """Rewrite a frame at PNG level 9 (lossless: the same pixels), atomically like the writer."""
    image = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    temp = png.with_name(f".{png.stem}.tmp.png")
    if not cv2.imwrite(str(temp), image, _PNG_SMALLEST):
        raise OSError(f"could not write {temp}")
    os.replace(temp, png)


def _readme(recipe: Recipe, spec: BoardSpec, frames: int, size: tuple[int, int]) -> str:
    camera = LENSES[recipe.lens]
    hfov, vfov = camera.field_of_view_deg()
    return f"""# {recipe.name}

Simulated capture: {recipe.purpose}.

- Lens: `{recipe.lens}` ({camera.model} model, {size[0]}x{size[1]}, {hfov:.0f} x {vfov:.0f} deg field of view)
- Hand: `{recipe.style}` path, {recipe.seconds:g} s at {recipe.fps:g} fps = {frames} frames, seed {recipe.seed}
- Board: {spec.describe()}
- Rendering: supersampled ray casting through the lens model, lens blur {BLUR_SIGMA_PX} px, sensor noise
  {NOISE_SIGMA_DN} DN, 20% vignetting, 20 ms exposure (motion blur), sRGB-like gamma
- Ground truth: `truth.json` holds the true camera model and every frame's board pose (T_cam_board, metres)

Regenerate with `.venv/bin/python recordings/make_recordings.py --out recordings --only {recipe.name}`.

Licence: generated by calibcoach; CC0 1.0 (public domain dedication).
"""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder that receives the recording folders")
    parser.add_argument("--only", action="append", choices=[r.name for r in RECIPES],
                        help="regenerate just this recording (repeatable)")
    args = parser.parse_args(argv)
    spec = BoardSpec(legacy=False, inverted=False)
    args.out.mkdir(parents=True, exist_ok=True)
    for recipe in RECIPES:
        if args.only and recipe.name not in args.only:
            continue
        start = time.monotonic()
        frames, size_mb = make_recording(recipe, args.out, spec)
        print(f"{recipe.name}: {frames} frames, {size_mb:.1f} MB, {time.monotonic() - start:.0f} s", flush=True)
    total = folder_size_mb(args.out)
    print(f"{args.out}: {total:.1f} MB in total (budget {BUDGET_MB:g} MB)")
    if total > BUDGET_MB:
        print(f"over budget: lower the frame counts in RECIPES of {Path(__file__).name}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
