"""Handheld board trajectories: how a person moves a ChArUco board in front of a fixed camera.

Targets are chosen in image space (a pixel for the board centre, a distance, a tilt), and the
board pose that realises each target is solved through the lens model. That keeps coverage
predictable for any lens: "top-left corner" means the top-left corner of the image on a 70 deg
webcam and on a 150 deg fisheye alike. Between targets the board moves with a minimum-jerk
profile (how arm movements accelerate), and a smooth tremor is added on top.

Styles (what a calibration tool must cope with):
- "careful": quadrants, edges, corners and centre; tilts of 0, 20, 35, 50 deg about both board
  axes with both signs; near (~70% of the image height), mid (~45%) and far (~25%); 0.5-1 s
  dwells; sub-millimetre tremor; the board kept fully inside the image.
- "sloppy": quick swings (motion blur), short dwells, the board partly out of the image, now
  and then lowered out of view, uneven coverage, millimetre tremor.
- "frontal": roughly frontal (tilt < 8 deg), near the centre, one distance: the capture that
  calibrates to a low RMS and is badly wrong at the image edges.

Angles follow docs/conventions.md: tilt_x positive = top edge further away, tilt_y positive =
right edge further away, both measured against the line of sight to the board centre.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from calibcoach.drivers import geometry
from calibcoach.drivers.geometry import facing_orientation, pose_facing_pixel, tilt_against_sight_deg
from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.sim_render import interpolate_pose, pose_matrix

if TYPE_CHECKING:  # drivers is the bottom layer: the board type is only named, never imported at run time
    from calibcoach.coverage.board import BoardSpec

STYLES = ("careful", "sloppy", "frontal")
MIN_DEPTH_M = 0.15  # every board point stays at least this far in front of the camera (z, metres)
# Board height as a share of the image height, measured frontally at the image centre.
HEIGHT_SHARE = {"near": 0.70, "mid": 0.45, "far": 0.25}
_FIT_MARGIN = 0.015  # careful style: the board keeps 1.5% of the image width from every edge

# The careful session: (image position as a share of (width, height), distance, tilt_x, tilt_y).
# The first five visit the centre and the four quadrants, the next four the corners, then big
# tilts and the edges; the first thirteen hold every signed single-axis tilt (20, 35, 50 deg) once,
# so even a 15 s recording covers most of them. Targets are pushed inwards until the board fits,
# so a corner target puts the board's corner into the image corner. The corners use "mid":
# at "far" an 8x11 board has ~16 px squares on a 720p webcam and is barely detected (the far
# targets at the bottom and left edges show that failure mode on purpose).
_CAREFUL_TARGETS: tuple[tuple[tuple[float, float], str, float, float], ...] = (
    ((0.50, 0.50), "near", 0.0, 0.0),
    ((0.27, 0.28), "mid", 35.0, 0.0),
    ((0.73, 0.28), "mid", 0.0, -35.0),
    ((0.73, 0.72), "mid", -35.0, 0.0),
    ((0.27, 0.72), "mid", 0.0, 35.0),
    ((0.00, 0.00), "mid", 20.0, 0.0),
    ((1.00, 0.00), "mid", 0.0, -20.0),
    ((1.00, 1.00), "mid", -20.0, 0.0),
    ((0.00, 1.00), "mid", 0.0, 20.0),
    ((0.50, 0.50), "near", 50.0, 0.0),
    ((0.50, 0.50), "near", 0.0, -50.0),
    ((0.50, 0.00), "mid", -50.0, 0.0),
    ((1.00, 0.50), "mid", 0.0, 50.0),
    ((0.50, 0.85), "far", 35.0, 0.0),
    ((0.00, 0.50), "mid", 0.0, -35.0),
    ((0.30, 0.45), "far", 0.0, -35.0),
    ((0.50, 0.50), "mid", 20.0, 20.0),
)


@dataclass(frozen=True, slots=True)
class Pose:
    """The true board pose in one frame."""

    index: int  # frame index, 0-based
    timestamp_ns: int  # index / fps
    rvec: np.ndarray  # (3,) float64 Rodrigues, T_cam_board
    tvec: np.ndarray  # (3,) float64 metres, T_cam_board


@dataclass(frozen=True, slots=True)
class _Key:
    """A keyframe of the path: where the board centre is and how the board is turned."""

    centre_m: np.ndarray  # (3,) float64 board centre in the camera frame, metres
    rvec: np.ndarray  # (3,) float64 board orientation (R_cam_board as Rodrigues)
    move_s: float  # time to arrive here from the previous keyframe
    dwell_s: float  # time held here before leaving


def board_centre_m(spec: BoardSpec) -> np.ndarray:
    """(3,) float64 centre of the chessboard area in the board frame, metres."""
    return geometry.board_centre_m(spec.squares_x, spec.squares_y, spec.square_mm / 1000.0)


def board_outline_m(spec: BoardSpec, *, per_edge: int = 12, margin_squares: float = 0.0) -> np.ndarray:
    """(4 * per_edge, 3) float64 points along the chessboard's outline (grown by `margin_squares`).

    Sampled along the edges, not just the four corners: through a fisheye a straight edge bows
    outwards, so the corners alone underestimate how far the board reaches.
    """
    sq = spec.square_mm / 1000.0
    x0, y0 = -margin_squares * sq, -margin_squares * sq
    x1, y1 = (spec.squares_x + margin_squares) * sq, (spec.squares_y + margin_squares) * sq
    s = np.linspace(0.0, 1.0, per_edge, endpoint=False)
    edges = [
        np.stack([x0 + s * (x1 - x0), np.full_like(s, y0)], 1),
        np.stack([np.full_like(s, x1), y0 + s * (y1 - y0)], 1),
        np.stack([x1 - s * (x1 - x0), np.full_like(s, y1)], 1),
        np.stack([np.full_like(s, x0), y1 - s * (y1 - y0)], 1),
    ]
    xy = np.concatenate(edges)
    return np.concatenate([xy, np.zeros((xy.shape[0], 1))], axis=1)


def image_points(camera: CameraModel, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project (N, 3) camera-frame points; returns ((N, 2) pixels, (N,) bool "really seen there").

    A point counts as seen when it is in front of the camera and unprojecting its pixel gives
    its own direction back: beyond the fold of an over-fitted radial polynomial, `project` puts
    points far outside the field of view back inside the image, which must not count.
    """
    pts = np.asarray(points_cam, np.float64).reshape(-1, 3)
    px = camera.project(pts)
    finite = np.all(np.isfinite(px), axis=1)
    direction = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    back = camera.unproject(np.where(finite[:, None], px, 0.0))
    consistent = np.sum(back * direction, axis=1) > np.cos(1e-4)
    return px, finite & consistent


def _inside(camera: CameraModel, px: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
    w, h = camera.image_size
    return (px[:, 0] >= margin_px - 0.5) & (px[:, 0] <= w - 0.5 - margin_px) & (px[:, 1] >= margin_px - 0.5) & (
        px[:, 1] <= h - 0.5 - margin_px)


def place_board(
    camera: CameraModel,
    spec: BoardSpec,
    centre_px: tuple[float, float],
    distance_m: float,
    *,
    tilt_x_deg: float = 0.0,
    tilt_y_deg: float = 0.0,
    roll_deg: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """T_cam_board that shows the board centre at pixel `centre_px`, `distance_m` away along its ray.

    Returns (rvec (3,), tvec (3,) metres). The tilts are relative to the line of sight, so a board
    at the edge of a fisheye image with zero tilt faces the camera, as a person would hold it.

    Example:
        >>> rvec, tvec = place_board(LENSES["webcam720"], BoardSpec(), (320, 180), 0.8, tilt_x_deg=35)  # doctest: +SKIP
    """
    ray = camera.unproject(np.asarray(centre_px, np.float64).reshape(1, 2))[0]
    return pose_facing_pixel(ray, board_centre_m(spec), distance_m, tilt_x_deg=tilt_x_deg, tilt_y_deg=tilt_y_deg,
                             roll_deg=roll_deg)


def board_tilt_deg(rvec: np.ndarray, tvec: np.ndarray, spec: BoardSpec) -> tuple[float, float, float]:
    """(tilt, tilt_x, tilt_y) in degrees of the board against the line of sight to its centre.

    The same code as `calibcoach.coverage.pose` uses (`geometry.tilt_against_sight_deg`).
    """
    R = pose_matrix(rvec)
    centre = R @ board_centre_m(spec) + np.asarray(tvec, np.float64).reshape(3)
    return tilt_against_sight_deg(R[:, 2], centre)


def distance_for_height(camera: CameraModel, spec: BoardSpec, share: float) -> float:
    """Distance (m) at which a frontal board at the principal point spans `share` of the image height."""
    outline = board_outline_m(spec, per_edge=24)
    h = camera.image_size[1]
    lo, hi = MIN_DEPTH_M, 50.0
    for _ in range(50):  # bisection on a monotonic quantity: the farther, the smaller
        mid = np.sqrt(lo * hi)
        rvec, tvec = place_board(camera, spec, camera.principal_point, mid)
        px, seen = image_points(camera, outline @ pose_matrix(rvec).T + tvec)
        extent = np.ptp(px[seen, 1]) if np.all(seen) else np.inf
        lo, hi = (mid, hi) if extent > share * h else (lo, mid)
    return float(np.sqrt(lo * hi))


def _fit_inside(camera: CameraModel, spec: BoardSpec, target_px: np.ndarray, distance_m: float, tilt_x: float,
                tilt_y: float, roll: float) -> tuple[np.ndarray, float]:
    """Move a target inwards (and back if needed) until the whole board shows inside the image.

    Returns the adjusted (centre pixel (2,), distance). The careful user keeps all corners in view:
    each step shifts the centre by the outline's overflow (x1.1), moves it 15% towards the centre
    while part of the board would come closer than MIN_DEPTH_M, or steps 10% back when the board
    is larger than the image.
    """
    w, h = camera.image_size
    margin = _FIT_MARGIN * w
    outline = board_outline_m(spec, margin_squares=0.3)  # a little paper around the corners too
    centre = np.array(target_px, np.float64)
    for _ in range(40):
        rvec, tvec = place_board(camera, spec, centre, distance_m, tilt_x_deg=tilt_x, tilt_y_deg=tilt_y, roll_deg=roll)
        pts = outline @ pose_matrix(rvec).T + tvec
        px, seen = image_points(camera, pts)
        if np.min(pts[:, 2]) < MIN_DEPTH_M or not np.all(seen):
            # Too far off axis: at a fisheye's corner (86 deg) a board facing the camera would reach
            # behind the lens. Come 15% closer to the centre, or step back if already there.
            to_centre = np.array(camera.principal_point) - centre
            if np.linalg.norm(to_centre) < 1.0:
                distance_m *= 1.1
            else:
                centre += 0.15 * to_centre
            continue
        lo = np.array([margin - 0.5, margin - 0.5]) - px.min(axis=0)
        hi = px.max(axis=0) - np.array([w - 0.5 - margin, h - 0.5 - margin])
        if np.any((lo > 0) & (hi > 0)):
            distance_m *= 1.1  # wider or taller than the image at this distance
            continue
        shift = np.maximum(lo, 0.0) - np.maximum(hi, 0.0)
        if np.all(shift == 0):
            return centre, distance_m
        centre += 1.1 * shift
    return centre, distance_m


def _hidden_centre(camera: CameraModel, spec: BoardSpec, distance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A board centre (3,) and orientation (3,) below the image: the user has lowered the board.

    Starts just below the vertical field of view and lowers further until no outline point is
    seen, staying at least MIN_DEPTH_M in front of the camera.
    """
    outline = board_outline_m(spec, margin_squares=1.0)
    half_v = np.radians(camera.field_of_view_deg()[1] / 2)
    for extra_deg in range(10, 80, 5):
        angle = min(half_v + np.radians(extra_deg), np.radians(80))
        ray = np.array([0.0, np.sin(angle), np.cos(angle)])
        d = max(distance_m, (MIN_DEPTH_M + 0.2) / ray[2])  # 0.2 m: room for the tilted board's near edge
        R = facing_orientation(ray, 0.0, 0.0, 0.0)
        centre = d * ray
        pts = outline @ R.T + (centre - R @ board_centre_m(spec))
        px, seen = image_points(camera, pts)
        if not np.any(seen & _inside(camera, px)) and np.min(pts[:, 2]) >= MIN_DEPTH_M:
            break
    rvec, _ = cv2.Rodrigues(R)
    return centre, rvec.reshape(3)


def _min_jerk(tau: np.ndarray) -> np.ndarray:
    """Minimum-jerk position profile 0 -> 1 (Flash & Hogan 1985): zero velocity and acceleration at both ends."""
    tau = np.clip(tau, 0.0, 1.0)
    return tau**3 * (10 - 15 * tau + 6 * tau**2)


class _Tremor:
    """Smooth hand tremor: a few sinusoids at 4-11 Hz (physiological tremor) plus a 0.3-1 Hz sway."""

    def __init__(self, rng: np.random.Generator, *, translation_m: float, rotation_deg: float) -> None:
        self.freq_hz = np.concatenate([rng.uniform(4.0, 11.0, (3, 6)), rng.uniform(0.3, 1.0, (3, 6))], axis=0)
        self.phase = rng.uniform(0, 2 * np.pi, (6, 6))
        # amplitudes per component: rows 0-2 tremor, rows 3-5 sway (sway twice the tremor), columns
        # 0-2 translation, 3-5 rotation; divided by sqrt(3) so three sinusoids sum to about the amplitude.
        scale = np.array([translation_m] * 3 + [np.radians(rotation_deg)] * 3) / np.sqrt(3)
        self.amplitude = np.concatenate([np.ones((3, 1)), 2 * np.ones((3, 1))], axis=0) * scale[None, :]

    def at(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(translation (3,) metres, rotation (3,) Rodrigues) at time t_s."""
        values = np.sum(self.amplitude * np.sin(2 * np.pi * self.freq_hz * t_s + self.phase), axis=0)
        return values[:3], values[3:]


def _key_at(camera: CameraModel, spec: BoardSpec, centre_px, distance_m, tilt_x, tilt_y, roll, move_s, dwell_s,
            *, fit: bool) -> _Key:
    """The keyframe for an image-space target; `fit` first moves it until the whole board is in view."""
    centre_px = np.asarray(centre_px, np.float64)
    if fit:
        centre_px, distance_m = _fit_inside(camera, spec, centre_px, distance_m, tilt_x, tilt_y, roll)
    rvec, tvec = place_board(camera, spec, centre_px, distance_m, tilt_x_deg=tilt_x, tilt_y_deg=tilt_y, roll_deg=roll)
    centre = pose_matrix(rvec) @ board_centre_m(spec) + tvec
    return _Key(centre, rvec, move_s, dwell_s)


def _careful_keys(camera, spec, rng, seconds, distances) -> list[_Key]:
    """_CAREFUL_TARGETS in order (then mirrored, and again) until `seconds` are filled."""
    w, h = camera.image_size
    keys: list[_Key] = []
    total = 0.0
    passes = 0
    while total < seconds + 2.0:
        for (fx, fy), dist_name, tx, ty in _CAREFUL_TARGETS:
            sign = -1.0 if passes % 2 else 1.0  # the second pass mirrors the tilts
            pos = np.array([fx, fy]) + rng.normal(0, 0.02, 2)  # the user does not hit the spot exactly
            if passes % 2:
                pos = 1.0 - pos  # ... and mirrors the positions, so corners get both tilt signs
            move = 0.0 if not keys else rng.uniform(0.8, 1.3)  # an unhurried arm movement
            dwell = rng.uniform(0.5, 1.0)
            # Targets on the image border are partial views on purpose: the board centred on an image
            # corner shows about a quarter of its corners right where distortion is strongest.
            on_border = fx in (0.0, 1.0) or fy in (0.0, 1.0)
            keys.append(_key_at(camera, spec, pos * [w, h], distances[dist_name] * rng.uniform(0.93, 1.07),
                                sign * tx + rng.normal(0, 1.5), sign * ty + rng.normal(0, 1.5), rng.normal(0, 5.0),
                                move, dwell, fit=not on_border))
            total += move + dwell
            if total >= seconds + 2.0:
                break
        passes += 1
    return keys


def _sloppy_keys(camera, spec, rng, seconds, distances) -> list[_Key]:
    """Quick random swings around a favourite spot, partly out of the image, lowered every 5-9 s."""
    w, h = camera.image_size
    favourite = rng.uniform(0.2, 0.8, 2)  # where this user keeps returning: coverage is uneven
    tilt_choices = np.array([0.0, 20.0, 35.0, 50.0])
    keys: list[_Key] = []
    total, next_drop = 0.0, rng.uniform(3.0, 7.0)
    while total < seconds + 2.0:
        move = 0.0 if not keys else rng.uniform(0.3, 0.6)
        dwell = rng.uniform(0.0, 0.25)
        if total > next_drop:  # the board is lowered out of view for a moment
            centre, rvec = _hidden_centre(camera, spec, distances["mid"])
            keys.append(_Key(centre, rvec, move, rng.uniform(0.4, 1.0)))
            next_drop = total + rng.uniform(5.0, 9.0)
        else:
            pos = favourite + rng.normal(0, 0.18, 2) if rng.random() < 0.6 else rng.uniform(-0.1, 1.1, 2)
            pos = np.clip(pos, -0.15, 1.15)  # up to ~half the board may leave the image
            tilt = rng.choice(tilt_choices) * rng.choice([-1.0, 1.0])
            tx, ty = (tilt, rng.normal(0, 8)) if rng.random() < 0.5 else (rng.normal(0, 8), tilt)
            dist = rng.uniform(distances["near"], distances["far"])
            keys.append(_key_at(camera, spec, pos * [w, h], dist, tx, ty, rng.normal(0, 15.0), move, dwell, fit=False))
        total += keys[-1].move_s + keys[-1].dwell_s
    return keys


def _frontal_keys(camera, spec, rng, seconds, distances) -> list[_Key]:
    """Small wanders around the image centre at the "mid" distance, never tilted beyond 3 deg."""
    w, h = camera.image_size
    keys: list[_Key] = []
    total = 0.0
    dist = distances["mid"]
    while total < seconds + 2.0:
        pos = 0.5 + rng.uniform(-0.04, 0.04, 2)  # within 4% of the centre: ~3 deg off axis at 70 deg FOV
        move = 0.0 if not keys else rng.uniform(0.8, 1.5)
        # |tilt| <= 3 deg per axis plus 4 deg of line-of-sight angle stays below 8 deg even
        # measured against the optical axis.
        keys.append(_key_at(camera, spec, pos * [w, h], dist * rng.uniform(0.98, 1.02), rng.uniform(-3, 3),
                            rng.uniform(-3, 3), rng.uniform(-3, 3), move, rng.uniform(0.5, 1.5), fit=False))
        total += keys[-1].move_s + keys[-1].dwell_s
    return keys


_TREMOR = {"careful": (0.0003, 0.03), "sloppy": (0.002, 0.4), "frontal": (0.0003, 0.03)}  # (metres, degrees)


class Trajectory:
    """A continuous handheld board path: keyframes joined by minimum-jerk moves, plus tremor.

    `pose_at` evaluates it at any time, which the simulated camera uses to place the sub-frames
    of a frame's exposure on the real path (interpolating between frames 200 ms apart would start
    a move's blur before the hand moves). Build one with `handheld_trajectory`.
    """

    def __init__(self, spec: BoardSpec, keys: list[_Key], tremor: _Tremor) -> None:
        self._keys = keys
        self._tremor = tremor
        self._c_board = board_centre_m(spec)
        self._corners = board_outline_m(spec, per_edge=1)  # (4, 3) for the depth check
        # Timeline: key k is reached at arrive[k] and left at arrive[k] + dwell.
        self._arrive = np.cumsum([k.move_s for k in keys]) + np.cumsum([0.0] + [k.dwell_s for k in keys[:-1]])

    @property
    def duration_s(self) -> float:
        """Time at which the last keyframe is left; the path holds still after it."""
        return float(self._arrive[-1] + self._keys[-1].dwell_s)

    def pose_at(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """T_cam_board at time t_s: (rvec (3,), tvec (3,) metres)."""
        keys, arrive = self._keys, self._arrive
        k = int(np.searchsorted(arrive, t_s, side="right")) - 1  # the last key reached
        if k < 0:
            centre, rvec = keys[0].centre_m, keys[0].rvec
        elif k + 1 >= len(keys) or t_s <= arrive[k] + keys[k].dwell_s:
            centre, rvec = keys[k].centre_m, keys[k].rvec
        else:  # moving from key k to key k + 1
            nxt = keys[k + 1]
            s = float(_min_jerk(np.array((t_s - arrive[k] - keys[k].dwell_s) / nxt.move_s)))
            rvec, centre = interpolate_pose(keys[k].rvec, keys[k].centre_m, nxt.rvec, nxt.centre_m, s)
        shake_t, shake_r = self._tremor.at(t_s)
        R = pose_matrix(shake_r) @ pose_matrix(rvec)
        tvec = centre + shake_t - R @ self._c_board
        depth = (self._corners @ R.T + tvec)[:, 2]
        if depth.min() < MIN_DEPTH_M:  # a swing that would bring a corner too close: the arm stops short
            tvec = tvec + np.array([0.0, 0.0, MIN_DEPTH_M - depth.min()])
        r_out, _ = cv2.Rodrigues(R)
        return r_out.reshape(3), tvec

    def sample(self, *, seconds: float, fps: float) -> list[Pose]:
        """One Pose per frame: round(seconds * fps) frames, frame i at i / fps."""
        poses = []
        for i in range(int(round(seconds * fps))):
            rvec, tvec = self.pose_at(i / fps)
            poses.append(Pose(i, int(round(i * 1e9 / fps)), rvec, tvec))
        return poses


def handheld_trajectory(camera: CameraModel, spec: BoardSpec, style: str, *, seconds: float, seed: int,
                        tremor_scale: float = 1.0) -> Trajectory:
    """The continuous path behind `handheld_path` (same arguments but fps); see its docstring.

    `tremor_scale` multiplies the style's tremor and sway (4: a shaky hand), for benches that must
    hold from a steady hand to a shaky one.
    """
    if tremor_scale < 0:
        raise ValueError(f"tremor_scale must be >= 0, got {tremor_scale}")
    if style not in STYLES:
        raise ValueError(f"style must be one of {STYLES}, got {style!r}")
    if seconds <= 0:
        raise ValueError(f"seconds must be positive, got {seconds}")
    rng = np.random.default_rng(seed)
    distances = {name: distance_for_height(camera, spec, share) for name, share in HEIGHT_SHARE.items()}
    keys = {"careful": _careful_keys, "sloppy": _sloppy_keys, "frontal": _frontal_keys}[style](
        camera, spec, rng, seconds, distances)
    tremor = _Tremor(rng, translation_m=_TREMOR[style][0] * tremor_scale, rotation_deg=_TREMOR[style][1] * tremor_scale)
    return Trajectory(spec, keys, tremor)


def handheld_path(camera: CameraModel, spec: BoardSpec, style: str, *, seconds: float, fps: float, seed: int) -> list[Pose]:
    """Board poses of a handheld capture in front of a fixed camera, one per frame.

    Args:
        camera: the lens; targets are placed in its image, so coverage is the same for any lens.
        spec: the board (its size sets the distances for "near", "mid", "far").
        style: "careful", "sloppy" or "frontal" (see the module docstring).
        seconds: duration; the path has round(seconds * fps) frames.
        fps: frame rate; frame i is at i / fps.
        seed: every random choice (jitter, timing, tremor) derives from it: same seed, same path.
    Returns:
        list of Pose, T_cam_board per frame; every board corner at least MIN_DEPTH_M in front.

    Example:
        >>> poses = handheld_path(LENSES["webcam720"], BoardSpec(), "careful", seconds=20, fps=10, seed=1)  # doctest: +SKIP
        >>> len(poses)  # doctest: +SKIP
        200
    """
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    return handheld_trajectory(camera, spec, style, seconds=seconds, seed=seed).sample(seconds=seconds, fps=fps)
