"""Shared fixtures: paths to the bundled recordings and to the real captures in ../shared/data."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def recordings_dir(request: pytest.FixtureRequest) -> Path:
    return request.config.rootpath / "recordings"


@pytest.fixture(scope="session")
def shared_data(request: pytest.FixtureRequest) -> Path:
    """../shared/data beside the repo (CI has it); tests that need it skip with the reason when absent."""
    path = (request.config.rootpath / ".." / "shared" / "data").resolve()
    if not path.is_dir():
        pytest.skip(f"real captures not available: {path} is absent (it sits beside the repo on CI)")
    return path
