"""Write everything a finished session produces into the output folder.

Files other tools read as a camera (`camera_matrix.npy`, `dist_coeffs.npy`, `calibration.yaml`,
`camera_info.yaml`, DepthAI's JSON) only for a trusted result -- or, when the user accepts a
partial one, under names carrying "untrusted" --, `calibcoach`'s own `calibration.json` always, and
the board pose of every frame for hand-eye calibration (`board_poses.json`, same rule),
pictures a person reads (coverage map, tilt/distance bars, residual map, per-frame errors,
uncertainty map, undistorted check image), and `report.html` holding all of it for a person
(`html_report.py`), written for refused calibrations too.
"""

from __future__ import annotations

import io
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np

from calibcoach.app.export.common import untrusted_name
from calibcoach.app.export.handeye import write_board_poses
from calibcoach.app.outputs.files import (
    atomic_write_bytes,
    calibration_payload,
    write_calibration_json,
    write_npy,
    write_opencv_yaml,
    write_ros_camera_info,
)
from calibcoach.app.outputs.html_report import REPORT_NAME, write_html_report
from calibcoach.app.outputs.pictures import (
    bars_picture,
    board_pattern_picture,
    coverage_picture,
    per_frame_error_picture,
    residual_map_picture,
    save_png,
    uncertainty_picture,
    undistorted_check_picture,
)
from calibcoach.app.session import SessionResult
from calibcoach.app.solve.result import View
from calibcoach.coverage.grid import (
    DISTANCE_CELLS,
    TILT_CELLS,
    TILT_HISTOGRAM_EDGES_DEG,
)
from calibcoach.drivers.base import SourceInfo


def source_summary(info: SourceInfo, *, frames_read: int, replay_seconds: float, stopped_early: bool) -> dict:
    return {
        "description": info.description,
        "kind": info.kind,
        "camera_id": info.camera_id,
        "fps": info.fps,
        "frame_count": info.frame_count,
        "frames_read": frames_read,
        "replay_seconds": round(replay_seconds, 3),
        "stopped_early": stopped_early,
    }


def write_session_outputs(
    out_dir: Path,
    result: SessionResult,
    *,
    source_info: SourceInfo,
    command_line: Sequence[str],
    accept_partial: bool,
    replay_seconds: float,
    frames_read: int,
    stopped_early: bool,
    lens_state: dict | None = None,
) -> list[Path]:
    """Write all outputs; returns the paths written."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cal = result.calibration
    written: list[Path] = []
    for stale in CAMERA_FILES:  # never leave an earlier run's camera beside this result
        for name in (stale, untrusted_name(stale)):
            (out_dir / name).unlink(missing_ok=True)
    (out_dir / UNTRUSTED_NOTE).unlink(missing_ok=True)
    with ThreadPoolExecutor(max_workers=2, thread_name_prefix="pictures") as pool:
        drawn = _pictures(out_dir, result, pool)  # drawn while the files below are written
        coverage_summary = result.coverage.summary()
        coverage_summary["rejections"] = {k: v for k, v in result.rejections.items() if v}
        coverage_summary["frames_seen"] = result.frames_seen
        payload = calibration_payload(
            cal,
            verdict=result.verdict,
            model_choice=result.model_choice,
            uncertainty=result.uncertainty,
            coverage_summary=coverage_summary,
            board=result.board,
            source=source_summary(source_info, frames_read=frames_read, replay_seconds=replay_seconds, stopped_early=stopped_early),
            command_line=command_line,
            lens_state=dict(source_info.controls) if lens_state is None else lens_state,
        )
        payload["uncertainty"]["target_px"] = result.target_px
        payload["uncertainty"]["noise_px"] = result.noise_px
        payload["uncertainty"]["reachable_error_px"] = result.reachable_error_px  # E over the whole image a board can reach
        if result.expected_errors is not None:  # E from the model and from the scatter between holds; the larger is reported
            payload["uncertainty"]["expected_error_sources"] = result.expected_errors.summary()
        # frames the final solve left out as smeared in the exposure read off the capture (coverage/exposure.py)
        payload["smear"] = {"frames_left_out": result.smeared_left_out, "exposure": result.exposure}
        if result.residual_structure is not None:
            payload["residual_structure"] = result.residual_structure.summary()
        written.append(write_calibration_json(out_dir / "calibration.json", payload))
        if result.verdict.trusted or accept_partial:
            written += _camera_files(out_dir, result, camera_name=source_info.camera_id or "camera")
        written.append(write_detections(out_dir / "detections.npz", cal.views))
        pictures = [picture.result() for picture in drawn]
    written += pictures
    # the person's page, refused or not (it is a report, not a camera file: never in CAMERA_FILES)
    written.append(write_html_report(out_dir / REPORT_NAME, payload, pictures, accept_partial=accept_partial))
    return written


def _camera_files(out_dir: Path, result: SessionResult, *, camera_name: str) -> list[Path]:
    """The files other tools load as this camera; "_untrusted" in their names (and the verdict's
    reasons inside, where the format can hold them) unless the verdict trusted the calibration."""
    cal, camera = result.calibration, result.calibration.camera
    trusted = bool(result.verdict.trusted)
    suffix = "" if trusted else "_untrusted"
    written: list[Path] = []
    # A refused calibration writes nothing a downstream tool would load as a camera; with
    # --accept-partial every such file carries "untrusted" in its name and, where the format
    # can hold it, says so inside with the verdict's reasons.
    because = [] if trusted else list(result.verdict.reasons)
    written += list(write_npy(out_dir, camera, suffix=suffix))
    extra: dict[str, object] = {
        "frames_used": len(cal.views),
        "verdict": result.verdict.grade,
        "trusted": trusted,
        "expected_error_px": result.uncertainty.expected_error_px,
        "uncertainty_p95_covered_px": result.uncertainty.p95_covered_px,
        "uncertainty_p95_whole_image_px": result.uncertainty.p95_px,
    }
    if because:
        extra["untrusted_because"] = because
    written.append(write_opencv_yaml(out_dir / f"calibration{suffix}.yaml", camera, rms_px=cal.rms_px, extra=extra))
    written.append(write_ros_camera_info(out_dir / f"camera_info{suffix}.yaml", camera,
                                         camera_name=camera_name, untrusted_because=because))
    written.append(write_board_poses(out_dir / f"board_poses{suffix}.json", cal, untrusted_because=because))
    if because:
        note = ("This calibration was REFUSED by calibcoach and written only because --accept-partial was given.\n"
                "Its camera files carry 'untrusted' in their names. Why:\n" + "".join(f"- {r}\n" for r in because))
        written.append(atomic_write_bytes(out_dir / UNTRUSTED_NOTE, note.encode("utf-8")))
    return written


# Files a downstream tool loads as a camera: written for trusted calibrations, and under an
# "untrusted" name (`untrusted_name`) with --accept-partial; never for a refused one otherwise.
CAMERA_FILES = ("camera_matrix.npy", "dist_coeffs.npy", "calibration.yaml", "camera_info.yaml", "depthai_calibration.json",
                "board_poses.json")
__all__ = ["CAMERA_FILES", "UNTRUSTED_NOTE", "read_detections", "source_summary", "untrusted_name", "write_detections",
           "write_session_outputs"]
UNTRUSTED_NOTE = "UNTRUSTED.txt"


def write_detections(path: Path, views: Sequence[View]) -> Path:
    """The corners the final solve used, so it can be re-run or audited without the images.

    Arrays: `frame_index` (V,), `frame_name` (V,), `offsets` (V + 1,) into the concatenated
    `ids` (N,) int32, `image_points_px` (N, 2) float64 and `object_points_m` (N, 3) float64.
    """
    offsets = np.concatenate([[0], np.cumsum([v.ids.size for v in views])]).astype(np.int64)
    buffer = io.BytesIO()
    np.savez_compressed(
        buffer,
        frame_index=np.array([v.frame_index for v in views], np.int64),
        frame_name=np.array([v.frame_name for v in views]),
        offsets=offsets,
        ids=np.concatenate([v.ids for v in views]).astype(np.int32),
        image_points_px=np.concatenate([v.image_points_px for v in views]),
        object_points_m=np.concatenate([v.object_points_m for v in views]),
    )
    return atomic_write_bytes(path, buffer.getvalue())


def read_detections(path: Path) -> list[View]:
    """The views written by `write_detections`."""
    with np.load(path) as data:
        o = data["offsets"]
        return [
            View(int(data["frame_index"][i]), str(data["frame_name"][i]), data["ids"][o[i]:o[i + 1]],
                 data["image_points_px"][o[i]:o[i + 1]], data["object_points_m"][o[i]:o[i + 1]])
            for i in range(len(o) - 1)
        ]


def _pictures(out_dir: Path, result: SessionResult, pool: ThreadPoolExecutor) -> list[Future[Path]]:
    """Each picture drawn and saved on `pool`, in the report's order (OpenCV's drawing, colour maps
    and PNG encoding release the GIL, so they overlap each other and the files written meanwhile)."""
    cal = result.calibration
    size = cal.camera.image_size
    cov = result.coverage
    req = cov.requirements
    hist = cov.tilt_histograms()
    tilt_labels = [f"{int(a)}..{int(b)}" for a, b in zip(TILT_HISTOGRAM_EDGES_DEG[:-1], TILT_HISTOGRAM_EDGES_DEG[1:], strict=True)]
    labels = [v.frame_name or str(v.frame_index) for v in cal.views]
    drawings: list[tuple[str, Callable[[], np.ndarray]]] = [
        ("coverage.png", lambda: coverage_picture(size, [v.image_points_px for v in cal.views], cov.region_counts,
                                                  required=float(req.corners_per_region_cell))),
        ("tilt_distance.png", lambda: bars_picture([
            ("tilt (views / views needed)", [c.replace("_", " ") for c in TILT_CELLS],
             [cov.tilt_counts[c] / req.views_per_tilt_cell for c in TILT_CELLS]),
            ("distance (views / views needed)", list(DISTANCE_CELLS),
             [cov.distance_counts[c] / req.views_per_distance_cell for c in DISTANCE_CELLS]),
        ], title="Tilt and distance coverage", subtitle="green: requirement met; top edge / right edge away = positive tilt")),
        ("tilt_histogram.png", lambda: bars_picture([
            ("tilt about the image x axis, deg", tilt_labels, [float(v) for v in hist["tilt_x"]]),
            ("tilt about the image y axis, deg", tilt_labels, [float(v) for v in hist["tilt_y"]]),
        ], title="Tilts of the frames used", subtitle="views per tilt bin (the method asks for 30-60 deg both ways)",
            y_label="views")),
        ("residuals.png", lambda: residual_map_picture(size, np.concatenate([v.image_points_px for v in cal.views]),
                                                       np.concatenate(cal.residuals_px))),
        ("per_frame_errors.png", lambda: per_frame_error_picture(labels, cal.per_view_rms_px)),
        ("uncertainty.png", lambda: uncertainty_picture(result.uncertainty, target_px=result.target_px, image_size=size)),
    ]
    structure = result.residual_structure
    if structure is not None and structure.board.judged:
        drawings.append(("board_residuals.png", lambda: board_pattern_picture(structure, result.board)))
    if result.check_image is not None:
        check = result.check_image
        drawings.append(("undistorted_check.png", lambda: undistorted_check_picture(check, cal.camera)))
    return [pool.submit(lambda name=name, draw=draw: save_png(out_dir / name, draw())) for name, draw in drawings]
