"""`calibcoach export CALIB --to TARGET`: one calibration made earlier, written for one tool.

CALIB is a calibration.json or a folder holding one (any file `load_camera` reads works too). A
calibration calibcoach refused is exported only with --accept-partial, and then under untrusted
names with the reasons inside each file that can hold text (the project's trust rule).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from calibcoach.app.export.common import file_name
from calibcoach.app.export.isaac import write_isaac
from calibcoach.app.export.render import write_blender, write_mujoco
from calibcoach.app.export.sfm import write_colmap, write_kalibr, write_mrcal
from calibcoach.app.outputs.camera_reader import load_camera, load_trust
from calibcoach.app.outputs.files import write_npy, write_opencv_yaml, write_ros_camera_info
from calibcoach.drivers.errors import CalibcoachError
from calibcoach.drivers.lens import CameraModel


def _write_ros(out_dir: Path, camera: CameraModel, *, untrusted_because: Sequence[str] = ()) -> list[Path]:
    return [write_ros_camera_info(out_dir / file_name("camera_info.yaml", untrusted_because), camera,
                                  camera_name="calibcoach", untrusted_because=untrusted_because)]


def _write_opencv(out_dir: Path, camera: CameraModel, *, untrusted_because: Sequence[str] = ()) -> list[Path]:
    extra: dict[str, object] = {"trusted": not untrusted_because}
    if untrusted_because:
        extra["untrusted_because"] = list(untrusted_because)
    return [*write_npy(out_dir, camera, suffix="_untrusted" if untrusted_because else ""),
            write_opencv_yaml(out_dir / file_name("calibration.yaml", untrusted_because), camera, rms_px=None, extra=extra)]


WRITERS: dict[str, Callable[..., list[Path]]] = {
    "colmap": write_colmap,
    "kalibr": write_kalibr,
    "mrcal": write_mrcal,
    "isaac": write_isaac,
    "mujoco": write_mujoco,
    "blender": write_blender,
    "ros": _write_ros,
    "opencv": _write_opencv,
}
TARGETS = tuple(WRITERS)


def export_camera(camera: CameraModel, target: str, out_dir: str | Path, *, untrusted_because: Sequence[str] = ()) -> list[Path]:
    """Write `camera` for `target` into `out_dir`; returns the paths written."""
    if target not in WRITERS:
        raise CalibcoachError(f"unknown export target {target!r}; pass one of {', '.join(TARGETS)}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return WRITERS[target](out, camera, untrusted_because=list(untrusted_because))


def calibration_source(path: Path) -> Path:
    """The file to read: CALIB itself, or the calibration.json inside a folder."""
    if path.is_dir():
        inside = path / "calibration.json"
        if inside.is_file():
            return inside
        if any(path.glob("camera_matrix*.npy")):
            return path
        raise CalibcoachError(f"{path} holds no calibration.json; pass the --out folder of a calibcoach run or its calibration.json")
    if not path.exists():
        raise CalibcoachError(f"{path} does not exist; pass a calibration.json or the folder holding one")
    return path


def export_command(args: argparse.Namespace) -> int:
    source = calibration_source(Path(args.calibration))
    camera = load_camera(source)
    trusted, reasons = load_trust(source)
    if not trusted and not args.accept_partial:
        why = f" ({reasons[0]})" if reasons else ""
        raise CalibcoachError(f"{args.calibration} is a calibration calibcoach refused{why}; capture again, or pass "
                              "--accept-partial to export it anyway (the files are then named *_untrusted)")
    because = [] if trusted else (reasons or ["the source calibration was not trusted"])
    out = Path(args.out) if args.out else (source if source.is_dir() else source.parent)
    written = export_camera(camera, args.to, out, untrusted_because=because)
    print(f"wrote {', '.join(p.name for p in written)} to {out}" + (" (UNTRUSTED)" if because else ""))
    if because:
        print("calibcoach: this calibration was refused; every file says so and carries 'untrusted' in its name", file=sys.stderr)
    return 0
