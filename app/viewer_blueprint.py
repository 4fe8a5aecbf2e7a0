"""The viewer's layout: what a person a metre from the screen needs to see while holding a board.

Split out of `viewer.py` to keep that module short; like it, this is the only other place that
imports rerun. The live tab gives most of the screen to the camera (image, detected corners, the
ghost outline of where the board should go and the coverage heat map drawn over it), with a
narrow column on the right for the next instruction in large text, the progress curves and the
decision log. The report tab holds the verdict and the final pictures; the viewer opens on the
live tab and the person switches when the run ends.
"""

from __future__ import annotations

import rerun.blueprint as rrb

# Entity paths, shared with viewer.py so the layout and the logging cannot drift apart.
CAMERA = "camera"
IMAGE = "camera/image"
CORNERS = "camera/corners"
TARGET = "camera/target"  # the ghost board: the target pose's outline in perspective, with the sentence
TARGET_ARROW = "camera/target_arrow"  # from where the board is now to where it should go
COVERAGE = "camera/coverage"
GUIDANCE = "guidance"
DECISIONS = "log/decisions"
ACCEPTED = "progress/accepted"
COVERAGE_PCT = "progress/coverage_pct"
AXES = "camera/axes"
PROCESSED_FPS = "progress/processed_fps"
TILT_DISTANCE = "progress/tilt_distance"  # bars: frontal, top/bottom/left/right away, steep x/y, far, mid, near
EXPECTED_ERROR = "progress/expected_error_px"
ERROR_TARGET = "progress/error_target_px"
REPORT = "report"
VERDICT = "report/verdict"
PER_FRAME_RMS = "report/per_frame_rms_px"
RESIDUALS = "report/residuals"
REPORT_IMAGES = {  # entity path -> file name the report writes into the output folder
    "report/coverage": "coverage.png",
    "report/residual_map": "residuals.png",
    "report/board_residuals": "board_residuals.png",  # written only where enough board corners were seen in 3+ poses
    "report/uncertainty": "uncertainty.png",
    "report/undistorted_check": "undistorted_check.png",
    "report/per_frame_errors": "per_frame_errors.png",
}


def session_blueprint() -> rrb.Blueprint:
    """Live tab (big camera view + guidance, progress, log) and a report tab; panels collapsed.

    Panels (blueprint tree, selection, time) are collapsed because the person is holding a board,
    not a mouse: every pixel goes to the camera view and the instruction next to it.
    """
    live = rrb.Horizontal(
        rrb.Spatial2DView(origin=CAMERA, name="Camera"),
        rrb.Vertical(
            rrb.TextDocumentView(origin=GUIDANCE, name="Next move"),
            rrb.TimeSeriesView(origin="progress", contents=[f"+ /{ACCEPTED}", f"+ /{COVERAGE_PCT}", f"+ /{PROCESSED_FPS}"],
                               name="Frames kept / coverage % / processed fps"),
            rrb.TimeSeriesView(origin="progress", contents=[f"+ /{EXPECTED_ERROR}", f"+ /{ERROR_TARGET}"],
                               name="Expected error E vs target, px"),
            rrb.BarChartView(origin=TILT_DISTANCE, name="Tilts: frontal, top/bottom/left/right away, steep x/y | far, mid, near"),
            rrb.TextLogView(origin=DECISIONS, name="Decisions"),
            row_shares=[2, 1, 1, 1, 1],
        ),
        column_shares=[3, 1],
        name="Live",
    )
    report = rrb.Horizontal(
        rrb.Vertical(
            rrb.TextDocumentView(origin=VERDICT, name="Verdict"),
            rrb.BarChartView(origin=PER_FRAME_RMS, name="Per-frame RMS, px"),
            row_shares=[1, 1],
        ),
        rrb.Tabs(
            rrb.Spatial2DView(origin=RESIDUALS, name="Residual vectors"),
            *(rrb.Spatial2DView(origin=path, name=name.removesuffix(".png").replace("_", " "))
              for path, name in REPORT_IMAGES.items()),
        ),
        column_shares=[1, 2],
        name="Report",
    )
    # capture_time is the timeline every camera image is on: live previews are logged from the capture
    # thread at the camera's rate, before (and whether or not) their frame is processed.
    return rrb.Blueprint(rrb.Tabs(live, report, active_tab=0), rrb.TimePanel(state="collapsed", timeline="capture_time"),
                         collapse_panels=True)
