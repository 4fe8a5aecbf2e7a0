"""Isaac Sim USD, MuJoCo and Blender exports: numbers read back from the files, projections recomputed."""

from __future__ import annotations

import ast
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibcoach.app.export.isaac import write_isaac
from calibcoach.app.export.render import ideal_camera, write_blender, write_mujoco
from calibcoach.drivers.lens import CameraModel

SIZE = (1280, 720)
K = np.array([[912.3456789, 0.0, 641.2345], [0.0, 915.6789, 357.8912], [0.0, 0.0, 1.0]])
DIST = {
    "pinhole": [-0.291, 0.087, 0.00041, -0.00063, -0.0123],
    "rational": [0.41, -0.12, 0.0004, -0.0006, 0.011, 0.72, -0.08, 0.03],
    "fisheye": [0.061, -0.013, 0.0021, -0.0004],
}
MODELS = tuple(DIST)
TOLERANCE_PX = 0.01


def camera(model: str) -> CameraModel:
    return CameraModel(model, K, np.array(DIST[model]), SIZE)


def points_over_image(cam: CameraModel, n: int = 25, max_deg: float = 89.0) -> np.ndarray:
    w, h = cam.image_size
    u, v = np.meshgrid(np.linspace(0, w - 1, n), np.linspace(0, h - 1, n))
    rays = cam.unproject(np.stack([u.ravel(), v.ravel()], axis=1))
    rays = rays[rays[:, 2] > np.cos(np.radians(max_deg))]
    return rays / rays[:, 2:3] * np.linspace(0.5, 3.0, rays.shape[0])[:, None]


def script_constants(script: Path) -> dict:
    """The UPPER_CASE literal assignments at the top level of a generated script, parsed, never run."""
    tree = ast.parse(script.read_text())
    return {t.id: ast.literal_eval(node.value) for node in tree.body if isinstance(node, ast.Assign)
            for t in node.targets if isinstance(t, ast.Name) and t.id.isupper() and t.id != "CAMERA_OBJECT"}


# --- Isaac Sim ----------------------------------------------------------------------------------------


def usda_attributes(text: str) -> dict[str, tuple[str, str]]:
    """name -> (USD type, value text) of every attribute line inside the Camera prim."""
    return {m[2]: (m[1], m[3]) for m in re.finditer(r"^\s+(float|int2|token|bool) ([\w:]+) = (.+)$", text, re.M)}


@pytest.mark.parametrize("model", MODELS)
def test_isaac_usda_holds_the_opencv_lens_schema(tmp_path: Path, model: str) -> None:
    cam = camera(model)
    usda, _ = write_isaac(tmp_path, cam)
    text = usda.read_text()
    token, schema = ("opencvFisheye", "OmniLensDistortionOpenCvFisheyeAPI") if model == "fisheye" else \
        ("opencvPinhole", "OmniLensDistortionOpenCvPinholeAPI")
    assert text.startswith("#usda 1.0") and f'prepend apiSchemas = ["{schema}"]' in text
    attrs = usda_attributes(text)
    assert attrs["omni:lensdistortion:model"] == ("token", f'"{token}"')
    assert attrs[f"omni:lensdistortion:{token}:imageSize"] == ("int2", "(1280, 720)")
    lens = {name.rsplit(":", 1)[1]: np.float32(float(v)) for name, (kind, v) in attrs.items()
            if kind == "float" and name.startswith(f"omni:lensdistortion:{token}:")}
    names = ["k1", "k2", "k3", "k4"] if model == "fisheye" else ["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"][:len(DIST[model])]
    # what Isaac Sim gets: the schema's 32-bit floats; project with them and compare with the calibration
    K32 = np.array([[lens["fx"], 0, lens["cx"]], [0, lens["fy"], lens["cy"]], [0, 0, 1]], np.float64)
    read = CameraModel(model, K32, np.array([lens[n] for n in names], np.float64), SIZE)
    pts = points_over_image(cam)
    error = np.max(np.linalg.norm(read.project(pts) - cam.project(pts), axis=1))
    assert error < TOLERANCE_PX, f"Isaac {token} misses by {error:.2e} px"
    # the plain USD camera agrees with the same pinhole (tenths of a metre at metersPerUnit 1)
    f, ha, va = (float(attrs[n][1]) for n in ("focalLength", "horizontalAperture", "verticalAperture"))
    ho, vo = float(attrs["horizontalApertureOffset"][1]), float(attrs["verticalApertureOffset"][1])
    w, h = SIZE
    assert f / ha * w == pytest.approx(cam.fx, rel=1e-9) and f / va * h == pytest.approx(cam.fy, rel=1e-9)
    assert (w - 1) / 2 - ho / ha * w == pytest.approx(cam.principal_point[0], abs=1e-6)  # window shifted by +offset
    assert (h - 1) / 2 + vo / va * h == pytest.approx(cam.principal_point[1], abs=1e-6)


def test_isaac_script_applies_the_same_attributes(tmp_path: Path) -> None:
    cam = camera("rational")
    usda, script = write_isaac(tmp_path, cam)
    tree = ast.parse(script.read_text())  # valid Python (pxr is not here: read it, do not run it)
    values = script_constants(script)
    assert values["SCHEMA"] == "OmniLensDistortionOpenCvPinholeAPI" and values["MODEL_TOKEN"] == "opencvPinhole"
    assert values["IMAGE_SIZE"] == SIZE and values["TRUSTED"] is True
    lens = values["LENS_ATTRIBUTES"]
    expected = dict(zip(["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"], DIST["rational"], strict=True))
    expected.update(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2])
    assert lens == {f"omni:lensdistortion:opencvPinhole:{k}": v for k, v in expected.items()}
    usd = usda_attributes(usda.read_text())
    for name, metres in values["CAMERA_METRES"].items():  # the script's metres x 10 = the .usda's tenths
        assert float(usd[name][1]) == pytest.approx(metres * 10, rel=1e-12)
    calls = {n.func.attr for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute)}
    assert {"AddAppliedSchema", "CreateAttribute", "GetStageMetersPerUnit"} <= calls


def test_isaac_untrusted_files_say_so(tmp_path: Path) -> None:
    usda, script = write_isaac(tmp_path, camera("pinhole"), untrusted_because=["Coverage is only 40 %."])
    assert (usda.name, script.name) == ("isaac_camera_untrusted.usda", "isaac_apply_camera_untrusted.py")
    assert "UNTRUSTED" in usda.read_text() and "bool calibcoach:trusted = false" in usda.read_text()
    assert "TRUSTED = False" in script.read_text() and "Coverage is only 40 %." in script.read_text()
    ast.parse(script.read_text())


# --- MuJoCo ---------------------------------------------------------------------------------------------


def mujoco_K(element: ET.Element) -> np.ndarray:
    """K in OpenCV's pixels as MuJoCo computes it: compile (user_objects.cc, 32-bit intrinsic) and frustum."""
    res = [int(v) for v in element.get("resolution").split()]
    sensor = np.array(element.get("sensorsize").split(), np.float32)
    focal_px = np.array(element.get("focalpixel").split(), np.float32)
    principal_px = np.array(element.get("principalpixel").split(), np.float32)
    density = np.float32(res[0]) / sensor[0], np.float32(res[1]) / sensor[1]
    intrinsic = np.array([focal_px[0] / density[0], focal_px[1] / density[1],
                          principal_px[0] / density[0], principal_px[1] / density[1]], np.float32)
    fx, fy = intrinsic[0] / sensor[0] * res[0], intrinsic[1] / sensor[1] * res[1]
    # getFrustum: left of the axis (sensor_w / 2 - intrinsic[2]), above it (sensor_h / 2 + intrinsic[3]);
    # in pixels from the image's left / top edge, less half a pixel for OpenCV's pixel centres
    cx = (sensor[0] / 2 - intrinsic[2]) / sensor[0] * res[0] - 0.5
    cy = (sensor[1] / 2 + intrinsic[3]) / sensor[1] * res[1] - 0.5
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float64)


def bilinear(image: np.ndarray, px: np.ndarray) -> np.ndarray:
    return cv2.remap(image, px[:, 0:1].astype(np.float32), px[:, 1:2].astype(np.float32), cv2.INTER_LINEAR).ravel()


@pytest.mark.parametrize("model", MODELS)
def test_mujoco_camera_and_maps_rebuild_the_real_image(tmp_path: Path, model: str) -> None:
    cam = camera(model)
    xml, map_x_path, map_y_path = write_mujoco(tmp_path, cam)
    text = xml.read_text()
    assert "cannot hold lens distortion" in text
    element = ET.fromstring(text[text.index("<camera"):])  # the element after the comment
    assert element.tag == "camera" and element.get("fovy") is None and element.get("focal") is None
    ideal = ideal_camera(cam)
    np.testing.assert_allclose(mujoco_K(element), ideal.camera_matrix, atol=1e-3)
    map_x, map_y = np.load(map_x_path), np.load(map_y_path)
    assert map_x.shape == (SIZE[1], SIZE[0]) and map_x.dtype == np.float32
    # a point projected by the real model lands where the map sends its ideal (MuJoCo-rendered) pixel
    pts = points_over_image(cam, max_deg=65.0)
    real_px = cam.project(pts)
    inside = (real_px[:, 0] >= 0) & (real_px[:, 0] <= SIZE[0] - 1) & (real_px[:, 1] >= 0) & (real_px[:, 1] <= SIZE[1] - 1)
    real_px, pts = real_px[inside], pts[inside]
    ideal_px = (mujoco_K(element) @ (pts / pts[:, 2:3]).T).T[:, :2]  # what MuJoCo's pinhole renders
    sent = np.stack([bilinear(map_x, real_px), bilinear(map_y, real_px)], axis=1)
    error = np.max(np.linalg.norm(sent - ideal_px, axis=1))
    assert error < TOLERANCE_PX, f"MuJoCo map misses by {error:.2e} px"
    # and remap really produces the distorted image: a dot rendered at the ideal pixel appears at the real one
    render = np.zeros((SIZE[1], SIZE[0]), np.float32)
    target = ideal_px[len(ideal_px) // 3]
    cv2.circle(render, (int(round(target[0] * 16)), int(round(target[1] * 16))), 4 * 16, 1.0, -1, cv2.LINE_AA, shift=4)
    real = cv2.remap(render, map_x, map_y, cv2.INTER_LINEAR)
    ys, xs = np.nonzero(real > 0.5)
    assert np.hypot(xs.mean() - real_px[len(ideal_px) // 3, 0], ys.mean() - real_px[len(ideal_px) // 3, 1]) < 1.0


def test_ideal_camera_keeps_the_whole_real_field_in_the_render() -> None:
    cam = camera("pinhole")  # barrel: the real corners see wider than K says
    ideal = ideal_camera(cam)
    assert ideal.fx / cam.fx == pytest.approx(ideal.fy / cam.fy) and ideal.fx < cam.fx
    corners = cam.unproject(np.array([[-0.5, -0.5], [SIZE[0] - 0.5, SIZE[1] - 0.5], [-0.5, SIZE[1] - 0.5]]))
    px = ideal.project(corners)
    assert np.all(px >= -0.5 - 1e-6) and np.all(px[:, 0] <= SIZE[0] - 0.5 + 1e-6) and np.all(px[:, 1] <= SIZE[1] - 0.5 + 1e-6)


# --- Blender --------------------------------------------------------------------------------------------


def blender_K(values: dict) -> np.ndarray:
    """K from a Blender camera (the well-known bpy formula, sensor_fit HORIZONTAL, pixel centres at +0.5)."""
    w, h = values["RESOLUTION_X"], values["RESOLUTION_Y"]
    ratio = values["PIXEL_ASPECT_Y"] / values["PIXEL_ASPECT_X"]
    assert values["SENSOR_FIT"] == "HORIZONTAL"
    view_fac = w
    pixel_size = values["SENSOR_WIDTH_MM"] / values["LENS_MM"] / view_fac
    fx, fy = 1 / pixel_size, 1 / pixel_size / ratio
    cx = w / 2 - values["SHIFT_X"] * view_fac - 0.5
    cy = h / 2 + values["SHIFT_Y"] * view_fac / ratio - 0.5
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])


@pytest.mark.parametrize("model", MODELS)
def test_blender_script_recomputes_to_the_ideal_camera(tmp_path: Path, model: str) -> None:
    cam = camera(model)
    script, map_x, map_y = write_blender(tmp_path, cam)
    values = script_constants(script)
    np.testing.assert_allclose(blender_K(values), ideal_camera(cam).camera_matrix, atol=1e-9)
    assert values["PIXEL_ASPECT_X"] >= 1 and values["PIXEL_ASPECT_Y"] >= 1  # Blender's range
    assert "camera.shift_x = SHIFT_X" in script.read_text() and (map_x.name, map_y.name) == (
        "ideal_to_real_map_x.npy", "ideal_to_real_map_y.npy")


def test_blender_portrait_and_fy_above_fx(tmp_path: Path) -> None:
    cam = CameraModel("pinhole", np.array([[700.0, 0, 355.0], [0, 720.0, 650.0], [0, 0, 1]]), np.zeros(5), (720, 1280))
    (script, *_) = write_blender(tmp_path, cam)
    values = script_constants(script)
    np.testing.assert_allclose(blender_K(values), ideal_camera(cam).camera_matrix, atol=1e-9)
    assert values["PIXEL_ASPECT_X"] > 1


# --- read by the consumers' own parsers: Pixar's USD (usd-core) and MuJoCo's compiler -------------------


@pytest.mark.parametrize("model", MODELS)
def test_usd_itself_reads_the_isaac_camera_and_lens(tmp_path: Path, model: str) -> None:
    pytest.importorskip("pxr", reason="usd-core (Pixar's USD) is in the test extra: pip install -e '.[test]'")
    from pxr import Usd, UsdGeom
    cam = camera(model)
    usda, _ = write_isaac(tmp_path, cam)
    stage = Usd.Stage.Open(str(usda))
    prim = stage.GetPrimAtPath("/calibcoach_camera")
    assert prim.IsValid() and prim.GetTypeName() == "Camera"
    token = "opencvFisheye" if model == "fisheye" else "opencvPinhole"
    schema = "OmniLensDistortionOpenCvFisheyeAPI" if model == "fisheye" else "OmniLensDistortionOpenCvPinholeAPI"
    assert schema in prim.GetMetadata("apiSchemas").GetAddedOrExplicitItems()
    assert prim.GetAttribute("omni:lensdistortion:model").Get() == token

    def lens(name: str) -> float:
        return float(prim.GetAttribute(f"omni:lensdistortion:{token}:{name}").Get())

    assert tuple(prim.GetAttribute(f"omni:lensdistortion:{token}:imageSize").Get()) == SIZE
    names = ["k1", "k2", "k3", "k4"] if model == "fisheye" else ["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"][:len(DIST[model])]
    read = CameraModel(model, [[lens("fx"), 0, lens("cx")], [0, lens("fy"), lens("cy")], [0, 0, 1]],
                       np.array([lens(n) for n in names]), SIZE)
    pts = points_over_image(cam)
    assert np.max(np.linalg.norm(read.project(pts) - cam.project(pts), axis=1)) < TOLERANCE_PX
    gf = UsdGeom.Camera(prim).GetCamera()  # USD's own camera: focal length and apertures, same units
    w, h = SIZE
    assert gf.focalLength / gf.horizontalAperture * w == pytest.approx(cam.fx, rel=1e-6)
    assert gf.focalLength / gf.verticalAperture * h == pytest.approx(cam.fy, rel=1e-6)
    assert (w - 1) / 2 - gf.horizontalApertureOffset / gf.horizontalAperture * w == pytest.approx(cam.principal_point[0], abs=1e-3)


@pytest.mark.parametrize("model", MODELS)
def test_mujoco_compiles_the_camera_to_the_ideal_intrinsics(tmp_path: Path, model: str) -> None:
    mujoco = pytest.importorskip("mujoco", reason="mujoco is in the test extra: pip install -e '.[test]'")
    cam = camera(model)
    xml, _, _ = write_mujoco(tmp_path, cam)
    text = xml.read_text()
    element = text[text.index("<camera"):].strip()
    compiled = mujoco.MjModel.from_xml_string(f"<mujoco><worldbody>{element}</worldbody></mujoco>")
    res, sensor, intrinsic = compiled.cam_resolution[0], compiled.cam_sensorsize[0], compiled.cam_intrinsic[0]
    assert tuple(res) == SIZE
    # MuJoCo's frustum (engine_vis_visualize / getFrustum): focal length and principal offset in sensor units
    fx, fy = intrinsic[0] / sensor[0] * res[0], intrinsic[1] / sensor[1] * res[1]
    cx = (sensor[0] / 2 - intrinsic[2]) / sensor[0] * res[0] - 0.5  # OpenCV's pixel centres
    cy = (sensor[1] / 2 + intrinsic[3]) / sensor[1] * res[1] - 0.5
    np.testing.assert_allclose([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], ideal_camera(cam).camera_matrix, atol=2e-3)
