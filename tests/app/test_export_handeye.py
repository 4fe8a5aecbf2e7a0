"""board_poses.json: the final solve's board poses, good enough for cv2.calibrateHandEye to find the hand-eye X."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from calibcoach.app.export.handeye import load_board_poses, write_board_poses
from calibcoach.app.solve.result import Calibration, View
from calibcoach.drivers.lens import CameraModel


def transform(rvec, tvec) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64))[0]
    T[:3, 3] = tvec
    return T


def park_martin(R_gripper2base, t_gripper2base, R_target2cam, t_target2cam) -> tuple[np.ndarray, np.ndarray]:
    """Hand-eye AX = XB by Park & Martin (1994), the same inputs and outputs as cv2.calibrateHandEye.

    OpenCV 5.0.0's Python bindings lack calibrateHandEye (opencv/opencv#29565, exposed again by #29584),
    so the test solves it itself where cv2 cannot: G_i X C_i is the fixed board in the base frame, so
    A = G_j^-1 G_i and B = C_j C_i^-1 satisfy A X = X B.
    """
    G = [transform(cv2.Rodrigues(R)[0].ravel(), t.ravel()) for R, t in zip(R_gripper2base, t_gripper2base, strict=True)]
    C = [transform(cv2.Rodrigues(R)[0].ravel(), t.ravel()) for R, t in zip(R_target2cam, t_target2cam, strict=True)]
    pairs = [(np.linalg.inv(G[j]) @ G[i], C[j] @ np.linalg.inv(C[i])) for i in range(len(G)) for j in range(i + 1, len(G))]
    M = sum(np.outer(cv2.Rodrigues(B[:3, :3])[0].ravel(), cv2.Rodrigues(A[:3, :3])[0].ravel()) for A, B in pairs)
    w, V = np.linalg.eigh(M.T @ M)
    R = V @ np.diag(w**-0.5) @ V.T @ M.T
    lhs = np.vstack([A[:3, :3] - np.eye(3) for A, _ in pairs])
    rhs = np.concatenate([R @ B[:3, 3] - A[:3, 3] for A, B in pairs])
    return R, np.linalg.lstsq(lhs, rhs, rcond=None)[0].reshape(3, 1)


def test_calibrate_hand_eye_recovers_x_from_the_written_poses(tmp_path: Path) -> None:
    rng = np.random.default_rng(12)
    X = transform([0.1, -0.2, 0.05], [0.03, -0.01, 0.08])  # T_gripper_cam, the hand-eye answer
    T_base_board = transform([0.0, 0.0, 0.3], [0.6, 0.1, 0.0])
    grippers, rvecs, tvecs = [], [], []
    for _ in range(12):
        T_base_gripper = transform(rng.uniform(-0.5, 0.5, 3) + [np.pi, 0, 0], [0.5, 0.1, 0.5] + rng.uniform(-0.1, 0.1, 3))
        T_cam_board = np.linalg.inv(X) @ np.linalg.inv(T_base_gripper) @ T_base_board
        grippers.append(T_base_gripper)
        rvecs.append(cv2.Rodrigues(T_cam_board[:3, :3])[0].ravel())
        tvecs.append(T_cam_board[:3, 3])
    views = tuple(View(i * 7, f"frame_{i:03d}.png", np.arange(4, dtype=np.int32), np.zeros((4, 2)), np.zeros((4, 3)),
                       timestamp_ns=1_000_000_000 + i * 33_333_333) for i in range(12))
    cam = CameraModel("pinhole", np.array([[900.0, 0, 640], [0, 900.0, 360], [0, 0, 1]]), np.zeros(5), (1280, 720))
    cal = Calibration(cam, 0.2, views, np.array(rvecs), np.array(tvecs), tuple(np.zeros((4, 2)) for _ in views),
                      np.full(12, 0.2), ("fx",), np.eye(1))
    path = write_board_poses(tmp_path / "board_poses.json", cal)
    data = json.loads(path.read_text())
    assert data["trusted"] is True and "untrusted_because" not in data
    assert [f["name"] for f in data["frames"]] == [v.frame_name for v in views]
    assert [f["timestamp_ns"] for f in data["frames"]] == [v.timestamp_ns for v in views]
    np.testing.assert_allclose([f["tvec_m"] for f in data["frames"]], tvecs, atol=1e-15)
    R_target2cam, t_target2cam, frames = load_board_poses(path)
    R_gripper2base = [g[:3, :3] for g in grippers]
    t_gripper2base = [g[:3, 3:4] for g in grippers]
    solvers = [park_martin] + ([cv2.calibrateHandEye] if hasattr(cv2, "calibrateHandEye") else [])
    for solve in solvers:
        R, t = solve(R_gripper2base, t_gripper2base, R_target2cam, t_target2cam)
        np.testing.assert_allclose(R, X[:3, :3], atol=1e-6)
        np.testing.assert_allclose(np.asarray(t).ravel(), X[:3, 3], atol=1e-6)
    # the file's 4x4 and its rvec/tvec are the same pose
    f = frames[3]
    np.testing.assert_allclose(np.asarray(f["T_cam_board"]), transform(f["rvec"], f["tvec_m"]), atol=1e-12)


def test_untrusted_board_poses_say_so(tmp_path: Path) -> None:
    views = (View(0, "", np.arange(4, dtype=np.int32), np.zeros((4, 2)), np.zeros((4, 3))),)
    cam = CameraModel("pinhole", np.eye(3), np.zeros(5), (640, 480))
    cal = Calibration(cam, 0.2, views, np.zeros((1, 3)), np.array([[0, 0, 1.0]]), (np.zeros((4, 2)),), np.full(1, 0.2),
                      ("fx",), np.eye(1))
    path = write_board_poses(tmp_path / "board_poses_untrusted.json", cal, untrusted_because=["Coverage is only 40 %."])
    data = json.loads(path.read_text())
    assert data["trusted"] is False and data["untrusted_because"] == ["Coverage is only 40 %."]
    assert data["frames"][0]["timestamp_ns"] is None  # a view without a clock says so rather than inventing one
