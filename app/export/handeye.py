"""Hand-eye calibration input: the board pose of every frame the final solve used (board_poses.json).

For each frame: `T_cam_board` (4x4, board/target frame to camera frame, x_cam = R x_board + t,
metres), the same as `rvec` (Rodrigues, rad) and `tvec_m` (m), the frame's `index` in its source,
its `name` (image file name for folders) and `timestamp_ns` (the source's clock; null when the
solve's views carry none). These are exactly the poses of the final solve, with the final
intrinsics (given beside them): `R_target2cam`, `t_target2cam` of `cv2.calibrateHandEye` are
`T_cam_board[:3, :3]` and `T_cam_board[:3, 3]`. What is approximate is only what the solve is
(its residuals are in calibration.json); pair each frame with the robot pose at its timestamp.

Trust rule: written for trusted calibrations only, or with --accept-partial as
`board_poses_untrusted.json` carrying `"trusted": false` and the reasons.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from calibcoach.app.export.common import ascii_text
from calibcoach.app.outputs.files import atomic_write_bytes
from calibcoach.app.solve.result import Calibration
from calibcoach.drivers.errors import CalibcoachError

CONVENTION = ("T_cam_board maps board (target) coordinates to camera coordinates, x_cam = R @ x_board + t, "
              "metres; rvec is its Rodrigues vector (rad); OpenCV camera frame (x right, y down, z forward)")


def board_pose_records(calibration: Calibration) -> list[dict]:
    records = []
    for i, view in enumerate(calibration.views):
        rvec = np.asarray(calibration.rvecs[i], np.float64).reshape(3)
        tvec = np.asarray(calibration.tvecs[i], np.float64).reshape(3)
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(rvec)[0]
        T[:3, 3] = tvec
        stamp = getattr(view, "timestamp_ns", None)
        records.append({
            "index": int(view.frame_index),
            "name": view.frame_name,
            "timestamp_ns": None if stamp is None else int(stamp),
            "rvec": [float(v) for v in rvec],
            "tvec_m": [float(v) for v in tvec],
            "T_cam_board": [[float(v) for v in row] for row in T],
        })
    return records


def write_board_poses(path: str | Path, calibration: Calibration, *, untrusted_because: Sequence[str] = ()) -> Path:
    """Write board_poses.json (the caller picks the untrusted name; see the module docstring)."""
    cam = calibration.camera
    payload = {
        "trusted": not untrusted_because,
        **({"untrusted_because": [ascii_text(r) for r in untrusted_because]} if untrusted_because else {}),
        "convention": CONVENTION,
        "camera": {"model": cam.model, "image_size": list(cam.image_size),
                   "camera_matrix": cam.camera_matrix.tolist(), "dist_coeffs": cam.dist_coeffs.tolist()},
        "rms_px": float(calibration.rms_px),
        "frames": board_pose_records(calibration),
    }
    return atomic_write_bytes(path, (json.dumps(payload, indent=1) + "\n").encode("utf-8"))


def load_board_poses(path: str | Path) -> tuple[list[np.ndarray], list[np.ndarray], list[dict]]:
    """(R_target2cam list of (3, 3), t_target2cam list of (3, 1) metres, the frame records) from board_poses.json."""
    try:
        data = json.loads(Path(path).read_text())
        frames = data["frames"]
        T = [np.asarray(f["T_cam_board"], np.float64) for f in frames]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise CalibcoachError(f"{path} is not a calibcoach board_poses.json ({exc}); pass the one a calibrate run wrote") from None
    return [t[:3, :3] for t in T], [t[:3, 3:4] for t in T], frames
