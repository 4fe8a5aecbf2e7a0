"""The one error family of calibcoach.

Every error a user can cause or fix (a bad path, a wrong board, a camera that vanished) is a
`CalibcoachError` carrying a message that says what was found and what to do instead. The CLI
prints it on one line and exits with `exit_code`; nothing else in the project decides exit codes.
It lives in the bottom layer (drivers) so that every stage can raise it without importing upwards.
"""

from __future__ import annotations


class CalibcoachError(Exception):
    """A problem the user can fix; the message names the problem and the fix."""

    exit_code = 2


class SourceError(CalibcoachError):
    """A frame source cannot be opened or read (missing file, corrupt video, empty folder)."""


class BoardError(CalibcoachError):
    """The board in the images does not match the board calibcoach was told about."""


class CalibrationError(CalibcoachError):
    """The data cannot support a calibration (too few usable frames, degenerate views)."""


class InsufficientDataError(CalibcoachError):
    """A calibration was computed but coverage or uncertainty is not good enough to trust it."""

    exit_code = 3
