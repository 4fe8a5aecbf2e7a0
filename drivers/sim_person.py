"""A simulated person in a closed loop with the assistant: reads the guidance, moves, holds, repeats.

The open-loop paths of `sim_paths` cannot tell whether guidance helps; this person can. After each
hold they read the latest guidance and carry it out the way people do, not exactly:

- guided: go where `guidance.target` says: its image position, tilts and range, each off by a
  person's error (centre +-4% of the image, tilts +-6 deg, range +-8%, any roll of the board);
- careful: no feedback, a plan of their own (centre, quadrants, corners, edges, tilts of 0-50 deg
  about both axes with both signs, near, mid and far), the careful path of `sim_paths`;
- lazy: the board frontal near the centre, at arm's length, over and over.

Between holds the board moves with a minimum-jerk profile over 0.8-1.2 s (frames during the move
carry its motion blur), holds 0.8-1.2 s, and a smooth tremor (steady or shaky hand) rides on top.
Frames are rendered by the simulator's own renderer at `fps` and handed to a callback, which
returns the assistant's step (or None); the run ends when the step says done, or at `max_s`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.sim_paths import (
    _CAREFUL_TARGETS,
    HEIGHT_SHARE,
    MIN_DEPTH_M,
    _key_at,
    _min_jerk,
    _Tremor,
    board_centre_m,
    board_outline_m,
    distance_for_height,
)
from calibcoach.drivers.sim_render import (
    BoardRenderer,
    expose,
    interpolate_pose,
    motion_subframes,
    pose_matrix,
)

if TYPE_CHECKING:  # drivers is the bottom layer: the board type is only named, never imported at run time
    from calibcoach.coverage.board import BoardSpec

STRATEGIES = ("guided", "careful", "lazy")
# Tremor amplitude (metres, degrees), set from a real handheld 30 fps board video (shared/notes/
# guidance.md): its board moved a median 17 px/s at 1080p, ~11 px/s at 720p. "steady" reproduces
# that median on the 720p webcam at 0.6 m (12 px/s), "shaky" is 4x it (48 px/s, 1.6 px a frame),
# "very shaky" 10x (an arm held out for minutes, or a moving platform).
HANDS = {"steady": (0.00018, 0.022), "shaky": (0.0007, 0.09), "very shaky": (0.0018, 0.22)}
CENTRE_ERROR = 0.04  # share of the image width / height, 1 sigma
TILT_ERROR_DEG = 6.0
RANGE_ERROR = 0.08  # relative


@dataclass(frozen=True, slots=True)
class Hold:
    """One executed pose: what the person aimed for and when they held it."""

    start_s: float  # the hold begins (the move before it ends)
    end_s: float
    centre_px: tuple[float, float]  # aimed-at image position of the board centre (after the person's error)
    range_m: float
    tilt_x_deg: float
    tilt_y_deg: float
    asked: Any = None  # the guidance target that was being followed (guided), else None


@dataclass
class PersonRun:
    """What happened: the holds, the frames fed, when the assistant said done."""

    holds: list[Hold] = field(default_factory=list)
    frames: int = 0
    stopped_at_s: float | None = None  # capture time of the step that said done
    steps: list[Any] = field(default_factory=list)  # every non-None step the callback returned
    true_poses: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)  # T_cam_board of frame i at its timestamp


class SimulatedPerson:
    """A person holding the board in front of the (true) camera; see the module docstring.

    Args:
        camera: the true lens (the person aims in the image it forms).
        spec: the printed board.
        strategy: "guided", "careful" or "lazy".
        seed: every random choice (errors, timing, tremor, sensor noise) derives from it.
        fps: frames rendered per second of capture.
        hand: "steady" or "shaky" tremor.
        exposure_s: exposure time of every frame (motion blur).
        noise_sigma: sensor noise, 8-bit DN; low_light: dim room (darker, noisier).
        blur_sigma: lens blur, px.
        supersample: renderer samples per pixel per axis (1 keeps a 90 s run under a minute).
    """

    def __init__(self, camera: CameraModel, spec: BoardSpec, strategy: str, *, seed: int, fps: float = 10.0,
                 hand: str = "steady", exposure_s: float = 0.02, noise_sigma: float = 1.5, low_light: bool = False,
                 blur_sigma: float = 0.6, supersample: int = 1) -> None:
        if strategy not in STRATEGIES:
            raise ValueError(f"strategy must be one of {STRATEGIES}, got {strategy!r}")
        if hand not in HANDS:
            raise ValueError(f"hand must be one of {tuple(HANDS)}, got {hand!r}")
        self.camera, self.spec, self.strategy = camera, spec, strategy
        self.fps, self.exposure_s = float(fps), float(exposure_s)
        self.noise_sigma, self.low_light, self.blur_sigma = noise_sigma, low_light, blur_sigma
        self.rng = np.random.default_rng([seed, 7])
        self.seed = seed
        self.renderer = BoardRenderer(camera, spec, supersample, False, False)
        self.tremor = _Tremor(self.rng, translation_m=HANDS[hand][0], rotation_deg=HANDS[hand][1])
        self.distances = {name: distance_for_height(camera, spec, share) for name, share in HEIGHT_SHARE.items()}
        self._plan_index = 0
        self._c_board = board_centre_m(spec)
        self._corners = board_outline_m(spec, per_edge=1)
        self._paper = self.renderer.paper_corners_m()

    # --- what to do next ----------------------------------------------------------------------
    def _next_aim(self, target: Any) -> tuple[np.ndarray, float, float, float, float, bool]:
        """(centre_px (2,), range_m, tilt_x, tilt_y, roll, fit_inside) of the next hold."""
        w, h = self.camera.image_size
        rng = self.rng
        if self.strategy == "guided" and target is not None:
            centre = np.asarray(target.centre_px, np.float64) + rng.normal(0, CENTRE_ERROR, 2) * [w, h]
            return (centre, float(target.distance_m) * (1 + rng.normal(0, RANGE_ERROR)),
                    float(target.tilt_x_deg) + rng.normal(0, TILT_ERROR_DEG),
                    float(target.tilt_y_deg) + rng.normal(0, TILT_ERROR_DEG), float(rng.uniform(-180, 180)), False)
        if self.strategy == "careful":
            (fx, fy), dist_name, tx, ty = _CAREFUL_TARGETS[self._plan_index % len(_CAREFUL_TARGETS)]
            mirrored = (self._plan_index // len(_CAREFUL_TARGETS)) % 2 == 1
            self._plan_index += 1
            pos = np.array([fx, fy]) + rng.normal(0, 0.02, 2)
            sign = -1.0 if mirrored else 1.0
            if mirrored:
                pos = 1.0 - pos
            on_border = fx in (0.0, 1.0) or fy in (0.0, 1.0)
            return (pos * [w, h], self.distances[dist_name] * rng.uniform(0.93, 1.07), sign * tx + rng.normal(0, 1.5),
                    sign * ty + rng.normal(0, 1.5), float(rng.normal(0, 5.0)), not on_border)
        # lazy (and a guided person before any target): frontal, near the centre, at arm's length
        return (np.array([w, h]) * (0.5 + rng.uniform(-0.04, 0.04, 2)), self.distances["mid"] * rng.uniform(0.97, 1.03),
                float(rng.uniform(-3, 3)), float(rng.uniform(-3, 3)), float(rng.uniform(-3, 3)), False)

    # --- the loop -----------------------------------------------------------------------------
    def run(self, feed: Callable[[np.ndarray, int], Any], *, max_s: float = 120.0) -> PersonRun:
        """Hold, read the guidance, move, hold ... feeding every frame to `feed(image, timestamp_ns)`."""
        out = PersonRun()
        dt = 1.0 / self.fps
        t = 0.0
        last_step: Any = None
        here = None  # (board centre in the camera frame (3,), rvec (3,)) of the current hold
        while t < max_s:
            target = getattr(getattr(last_step, "guidance", None), "target", None)
            centre_px, range_m, tx, ty, roll, fit = self._next_aim(target)
            key = _key_at(self.camera, self.spec, centre_px, max(range_m, MIN_DEPTH_M + 0.05), tx, ty, roll, 0.0, 0.0, fit=fit)
            there = (key.centre_m, key.rvec)
            move_s = 0.0 if here is None else float(self.rng.uniform(0.8, 1.2))
            hold_s = float(self.rng.uniform(0.8, 1.2))
            start = here if here is not None else there
            segment_end = t + move_s + hold_s
            hold = Hold(t + move_s, segment_end, (float(centre_px[0]), float(centre_px[1])), float(range_m),
                        float(tx), float(ty), target)
            out.holds.append(hold)

            def pose_at(s: float, t0: float = t, a=start, b=there, move=move_s) -> tuple[np.ndarray, np.ndarray]:
                tau = 1.0 if move <= 0 else float(_min_jerk(np.array((s - t0) / move)))
                rvec, centre = interpolate_pose(a[1], a[0], b[1], b[0], tau)
                return self._with_tremor(s, centre, rvec)

            frame_t = np.ceil(t / dt - 1e-9) * dt
            while frame_t < segment_end and frame_t < max_s:
                out.true_poses.append(pose_at(frame_t))
                step = feed(self._render(pose_at, frame_t, out.frames), int(round(frame_t * 1e9)))
                out.frames += 1
                if step is not None:
                    out.steps.append(step)
                    last_step = step
                    if step.progress.done:
                        out.stopped_at_s = frame_t
                        return out
                frame_t += dt
            t = segment_end
            here = there
        return out

    def _with_tremor(self, t_s: float, centre: np.ndarray, rvec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        shake_t, shake_r = self.tremor.at(t_s)
        R = pose_matrix(shake_r) @ pose_matrix(rvec)
        tvec = centre + shake_t - R @ self._c_board
        depth = (self._corners @ R.T + tvec)[:, 2]
        if depth.min() < MIN_DEPTH_M:
            tvec = tvec + np.array([0.0, 0.0, MIN_DEPTH_M - depth.min()])
        r_out, _ = cv2.Rodrigues(R)
        return r_out.reshape(3), tvec

    def _render(self, pose_at: Callable[[float], tuple[np.ndarray, np.ndarray]], t_s: float, index: int) -> np.ndarray:
        """The frame at capture time t_s: sub-frames over the exposure, centred on t_s (motion blur)."""
        half = self.exposure_s / 2
        here = pose_at(t_s)
        n = 1
        if half > 0:
            n = min(6, motion_subframes(self.camera, self._paper, pose_at(t_s - half), here)
                    + motion_subframes(self.camera, self._paper, here, pose_at(t_s + half)) - 1)
        poses = [here] if n <= 1 else [pose_at(t_s - half + (j + 0.5) * self.exposure_s / n) for j in range(n)]
        radiance = self.renderer.radiance_exposure(poses)
        return expose(radiance, rng=np.random.default_rng([self.seed, index]), blur_sigma_px=self.blur_sigma,
                      noise_sigma_dn=self.noise_sigma, low_light=self.low_light, vignetting=0.2,
                      off_axis_rad=self.renderer.off_axis_rad)
