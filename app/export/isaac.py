"""NVIDIA Isaac Sim / Omniverse RTX: a Camera prim with the OpenCV lens-distortion schema.

Two files: `isaac_camera.usda`, a layer holding one `def Camera` prim, and `isaac_apply_camera.py`,
a script that authors the same attributes on an existing prim through `pxr` (run it in Isaac
Sim's Script Editor or `python.sh isaac_apply_camera.py [stage.usd] [/World/Camera]`).

- pinhole / rational -> `OmniLensDistortionOpenCvPinholeAPI`: `omni:lensdistortion:model =
  "opencvPinhole"`, float `...:opencvPinhole:fx, fy, cx, cy` (pixels), `k1..k6, p1, p2` (the
  8-term rational model; pinhole leaves k4..k6 at 0; the thin-prism `s1..s4` stay 0), int2
  `...:imageSize` (width, height): exact.
- fisheye -> `OmniLensDistortionOpenCvFisheyeAPI`: `"opencvFisheye"`, `...:opencvFisheye:fx, fy,
  cx, cy, k1..k4, imageSize`: exact (the cv2.fisheye model).
- The schema's numbers are USD `float`s (32-bit): they carry ~7 significant digits, about 1e-4 px
  at the image edge. Pixel convention: OpenCV's (the schema reproduces OpenCV's calibration; NVIDIA's
  own example checks a render against cv2.projectPoints with the same numbers).
- `focalLength`, `horizontalAperture`, `verticalAperture` and the aperture offsets are USD's plain
  camera. With a lens-distortion schema applied the renderer projects with the schema and uses
  focalLength only for depth of field; they are still written consistently (approximated only in
  that the pixel pitch is a nominal 3 um -- a calibration does not measure it): focalLength = fx *
  pitch, horizontalAperture = width * pitch, verticalAperture = height * pitch * fx / fy (so fy is
  exact too), offsets from the principal point. USD measures them in tenths of a scene unit: the
  .usda declares metersPerUnit = 1 (Isaac Sim's stage unit), so 1 mm is written 0.01; the script
  reads the stage's metersPerUnit and converts.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from calibcoach.app.export.common import ascii_text, notice_lines, num, out_path
from calibcoach.app.outputs.files import atomic_write_bytes
from calibcoach.drivers.lens import CameraModel

NOMINAL_PIXEL_PITCH_M = 3e-6
SCHEMA = {"fisheye": ("OmniLensDistortionOpenCvFisheyeAPI", "opencvFisheye")}
PINHOLE_SCHEMA = ("OmniLensDistortionOpenCvPinholeAPI", "opencvPinhole")
COEFF_ATTRS = {
    "pinhole": ("k1", "k2", "p1", "p2", "k3"),
    "rational": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "fisheye": ("k1", "k2", "k3", "k4"),
}


def schema_of(camera: CameraModel) -> tuple[str, str]:
    """(applied API schema, model token) for the camera's model."""
    return SCHEMA.get(camera.model, PINHOLE_SCHEMA)


def lens_attributes(camera: CameraModel) -> dict[str, float]:
    """The schema's float attributes by full name (model token and imageSize apart)."""
    _, token = schema_of(camera)
    cx, cy = camera.principal_point
    values = {"fx": camera.fx, "fy": camera.fy, "cx": cx, "cy": cy}
    values.update(zip(COEFF_ATTRS[camera.model], (float(v) for v in camera.dist_coeffs), strict=True))
    return {f"omni:lensdistortion:{token}:{k}": float(v) for k, v in values.items()}


def usd_camera_metres(camera: CameraModel, pitch_m: float = NOMINAL_PIXEL_PITCH_M) -> dict[str, float]:
    """UsdGeom.Camera's lens and filmback in metres (convert to tenths of a scene unit to author them).

    The offsets put the principal point where the calibration has it: USD shifts the film window
    by +offset (GfCamera: window = [offset - aperture / 2, offset + aperture / 2], y up), so the
    optical axis lands at (w - 1) / 2 - offset_x / pitch and (h - 1) / 2 + offset_y / pitch_y.
    """
    w, h = camera.image_size
    cx, cy = camera.principal_point
    pitch_y = pitch_m * camera.fx / camera.fy
    return {
        "focalLength": camera.fx * pitch_m,
        "horizontalAperture": w * pitch_m,
        "verticalAperture": h * pitch_y,
        "horizontalApertureOffset": ((w - 1) / 2.0 - cx) * pitch_m,
        "verticalApertureOffset": (cy - (h - 1) / 2.0) * pitch_y,
    }


def write_isaac(out_dir: str | Path, camera: CameraModel, *, untrusted_because: Sequence[str] = (),
                prim_name: str = "calibcoach_camera") -> list[Path]:
    return [_write_usda(out_dir, camera, untrusted_because, prim_name), _write_script(out_dir, camera, untrusted_because)]


def _write_usda(out_dir, camera: CameraModel, untrusted_because: Sequence[str], prim_name: str) -> Path:
    schema, token = schema_of(camera)
    w, h = camera.image_size
    doc = "calibcoach calibration" + (" (UNTRUSTED: " + "; ".join(ascii_text(r) for r in untrusted_because) + ")"
                                      if untrusted_because else "")
    lines = [
        "#usda 1.0",
        "(",
        f'    doc = "{doc.replace(chr(34), chr(39))}"',
        "    metersPerUnit = 1",
        ")",
        *notice_lines(untrusted_because),
        f"# {camera.model} model; lens and aperture in tenths of a scene unit (metersPerUnit 1: 1 mm = 0.01),",
        f"# nominal pixel pitch {NOMINAL_PIXEL_PITCH_M * 1e6:g} um; projection comes from the {schema} attributes",
        "",
        f'def Camera "{prim_name}" (',
        f'    prepend apiSchemas = ["{schema}"]',
        ")",
        "{",
    ]
    tenths = 10.0  # tenths of a scene unit per metre at metersPerUnit = 1
    lines += [f"    float {name} = {num(value * tenths)}" for name, value in usd_camera_metres(camera).items()]
    if untrusted_because:
        lines.append("    bool calibcoach:trusted = false")
    lines.append(f'    token omni:lensdistortion:model = "{token}"')
    lines += [f"    float {name} = {num(value)}" for name, value in lens_attributes(camera).items()]
    lines += [f"    int2 omni:lensdistortion:{token}:imageSize = ({w}, {h})", "}", ""]
    return atomic_write_bytes(out_path(out_dir, "isaac_camera.usda", untrusted_because), "\n".join(lines).encode("ascii"))


_SCRIPT = '''"""Apply a calibcoach calibration to a USD Camera prim (Isaac Sim / Omniverse, or plain pxr).

Usage: in Isaac Sim's Script Editor (the open stage), or
    python.sh isaac_apply_camera.py [stage.usd] [/World/calibcoach_camera]
"""

import sys

from pxr import Gf, Sdf, Usd, UsdGeom

SCHEMA = {schema!r}
MODEL_TOKEN = {token!r}
IMAGE_SIZE = ({w}, {h})
TRUSTED = {trusted!r}
UNTRUSTED_BECAUSE = {reasons!r}
# OpenCV lens-distortion attributes (pixels, OpenCV's pixel convention)
LENS_ATTRIBUTES = {{
{lens}
}}
# UsdGeom.Camera lens and filmback in metres (nominal {pitch_um:g} um pixel pitch); authored in tenths of a scene unit
CAMERA_METRES = {{
{metres}
}}


def apply(stage, prim_path):
    prim = stage.GetPrimAtPath(prim_path)
    if not prim.IsValid():
        prim = UsdGeom.Camera.Define(stage, prim_path).GetPrim()
    prim.AddAppliedSchema(SCHEMA)
    tenths_per_metre = 10.0 / UsdGeom.GetStageMetersPerUnit(stage)
    for name, metres in CAMERA_METRES.items():
        prim.CreateAttribute(name, Sdf.ValueTypeNames.Float).Set(metres * tenths_per_metre)
    prim.CreateAttribute("omni:lensdistortion:model", Sdf.ValueTypeNames.Token).Set(MODEL_TOKEN)
    for name, value in LENS_ATTRIBUTES.items():
        prim.CreateAttribute(name, Sdf.ValueTypeNames.Float).Set(value)
    prim.CreateAttribute("omni:lensdistortion:" + MODEL_TOKEN + ":imageSize", Sdf.ValueTypeNames.Int2).Set(Gf.Vec2i(*IMAGE_SIZE))
    if not TRUSTED:
        prim.CreateAttribute("calibcoach:trusted", Sdf.ValueTypeNames.Bool).Set(False)
        print("WARNING: untrusted calibration:", "; ".join(UNTRUSTED_BECAUSE))
    return prim


if __name__ == "__main__":
    if len(sys.argv) > 1:
        stage = Usd.Stage.Open(sys.argv[1])
    else:
        import omni.usd

        stage = omni.usd.get_context().get_stage()
    path = sys.argv[2] if len(sys.argv) > 2 else "/World/calibcoach_camera"
    apply(stage, path)
    if len(sys.argv) > 1:
        stage.GetRootLayer().Save()
'''


def _write_script(out_dir, camera: CameraModel, untrusted_because: Sequence[str]) -> Path:
    schema, token = schema_of(camera)
    w, h = camera.image_size
    text = _SCRIPT.format(
        schema=schema, token=token, w=w, h=h, trusted=not untrusted_because,
        reasons=[ascii_text(r) for r in untrusted_because], pitch_um=NOMINAL_PIXEL_PITCH_M * 1e6,
        lens="\n".join(f"    {name!r}: {num(v)}," for name, v in lens_attributes(camera).items()),
        metres="\n".join(f"    {name!r}: {num(v)}," for name, v in usd_camera_metres(camera).items()),
    )
    if untrusted_because:
        text = "\n".join(notice_lines(untrusted_because)) + "\n" + text
    return atomic_write_bytes(out_path(out_dir, "isaac_apply_camera.py", untrusted_because), text.encode("ascii"))
