"""The live session's solve, and the model it works with while the data is thin.

The final solve chooses the lens model by cross-validation (app/solve/model_choice.py); until then
the guidance needs intrinsics from the first few frames, and a pinhole model cannot follow a
fisheye even for that: its wrong focal length sends the person to ranges where the board is too
small to read. So while the solves are reduced (the bootstrap model), a pinhole that does not fit a
narrow lens is checked against a reduced fisheye, and the session works with the fisheye from then
on when it fits clearly better or the pinhole reads a field wider than 110 deg.
"""

from __future__ import annotations

from collections.abc import Sequence

from calibcoach.app.solve.calibrate import RawSolution, solve
from calibcoach.app.solve.model_choice import pinhole_sees_narrow_lens
from calibcoach.app.solve.result import View
from calibcoach.drivers.errors import CalibrationError
from calibcoach.drivers.lens import CameraModel

# The reduced fisheye's RMS below this share of the reduced pinhole's: a fisheye (on a 150 deg lens
# the reduced pinhole was seen to miss by 50 px of expected error and stall the capture).
FISHEYE_FITS_BETTER = 0.7
# The check's fisheye is solved to convergence (~0.6 s at 6-11 views of a 4x5 board: OpenCV re-poses
# every view in each of up to 100 iterations) only when its first 8 iterations fit within this share
# of the pinhole's RMS: the remaining ones would have to cut its RMS by a further 18% to pass 0.7,
# and on caliscope's 90 deg webcam they cut it by at most 0.02% (on a 105 deg render and a 150 deg
# one, by nothing). That webcam's capture checked six times and stayed pinhole: 4 s of its 15.
FISHEYE_MIGHT_FIT = 0.85
# A pinhole reading a field wider than this is taken for a fisheye without the check's solve.
PINHOLE_READS_FISHEYE_DEG = 110.0


def live_solve(views: Sequence[View], image_size: tuple[int, int], working_model: str, *, reduced: bool,
               may_switch: bool, initial: CameraModel | None) -> tuple[RawSolution | None, str]:
    """Solve `views` with the working model (reduced while the data is thin, from `initial` where it is
    of that model); returns the solution and the working model from now on (the solution None when
    the switch to a fisheye was decided and its solve failed: the next frames' solves try it again).

    `may_switch` (the model is "auto"): a pinhole working model becomes a fisheye when, on reduced
    solves, the lens shows itself to be one. Decided while the data is thin; later solves start
    from the working model.

    Raises:
        CalibrationError: the solve failed on these views.
    """
    raw = solve(views, image_size, working_model, reduced=reduced,
                initial=initial if initial is not None and initial.model == working_model else None)
    if not may_switch or working_model != "pinhole":
        return raw, working_model
    hfov = raw.camera.field_of_view_deg()[0]
    fisheye = None
    # The check's fisheye solve is skipped where the pinhole already fits a narrow lens (the model
    # choice's rule): it costs 5-8x the reduced pinhole, and on such a lens it came out no better.
    if reduced and not pinhole_sees_narrow_lens(raw.rms_px, hfov):
        try:  # converged only where its first iterations leave the fisheye a chance (`FISHEYE_MIGHT_FIT`)
            quick = solve(views, image_size, "fisheye", reduced=True, basin_only=True)
            if quick.rms_px < FISHEYE_MIGHT_FIT * raw.rms_px:
                fisheye = solve(views, image_size, "fisheye", reduced=True)
        except CalibrationError:
            pass
    if hfov > PINHOLE_READS_FISHEYE_DEG:
        if fisheye is not None:  # the check's solve is this very solve (same views, reduced)
            return fisheye, "fisheye"
        try:
            return solve(views, image_size, "fisheye", reduced=reduced), "fisheye"
        except CalibrationError:
            return None, "fisheye"
    if fisheye is not None and fisheye.rms_px < FISHEYE_FITS_BETTER * raw.rms_px:
        return fisheye, "fisheye"
    return raw, "pinhole"
