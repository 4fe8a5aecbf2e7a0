"""calibcoach: a live camera-calibration capture assistant.

The package root (this file lives in `app/_root/`, mapped onto `calibcoach` in pyproject.toml, so
the repository keeps its design-card layout). It holds the embedding API and nothing else; the
stages live in `calibcoach.drivers`, `calibcoach.coverage` and `calibcoach.app`. Names are
loaded on first use, so `import calibcoach.drivers.v4l2` does not pull in OpenCV's solvers.

    import calibcoach
    assistant = calibcoach.Assistant(board=calibcoach.BoardSpec(), image_size=(1280, 720))
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "Assistant": "calibcoach.app.assistant",
    "Step": "calibcoach.app.assistant",
    "Progress": "calibcoach.app.assistant",
    "Result": "calibcoach.app.assistant",
    "Guidance": "calibcoach.coverage.guidance",
    "Target": "calibcoach.coverage.guidance",
    "BoardSpec": "calibcoach.coverage.board",
    "CameraModel": "calibcoach.drivers.lens",
    "CalibrationError": "calibcoach.drivers.errors",
}
__all__ = sorted(_EXPORTS)
# The one place the version is written: pyproject.toml reads it from here ([tool.setuptools.dynamic]),
# and calibration.json takes it from here without importlib.metadata (~50 ms at the end of every
# calibration: it imports csv, email and zipfile and parses the installed metadata).
__version__ = "0.1.0"


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'calibcoach' has no attribute {name!r}")


def __dir__() -> list[str]:
    return __all__
