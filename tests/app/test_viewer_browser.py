"""The real web viewer in a real headless browser: the person's screen during a replayed session.

Debian's chromium renders Rerun's web viewer with software WebGL, which takes 15-30 s, so the page
is driven over the DevTools protocol and given that time before the screenshot. Marked `browser`
so it can be skipped locally (`pytest -m "not browser"`); CI installs chromium and runs it.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from calibcoach.app.replay import run_replay
from calibcoach.app.session import SessionSettings
from calibcoach.app.viewer import Viewer
from calibcoach.coverage.board import BoardSpec
from calibcoach.drivers.replay import open_source

from _browser import capture_screenshot, devtools_page, free_port

pytestmark = pytest.mark.browser
RENDER_WAIT_S = 35.0


def screenshot(url: str, out: Path, *, wait_s: float, ready=None) -> np.ndarray:
    """Open `url` in headless chromium and return a screenshot (BGR) once `ready(image)` holds.

    Screenshots are taken every few seconds from `wait_s / 2` on, up to `2 * wait_s`: software
    WebGL on a busy CI machine can take longer than on a quiet one, and a fixed sleep would flake.
    """
    with devtools_page(out.parent / "chromium-profile") as call:
        call("Page.enable")
        call("Page.navigate", url=url)
        time.sleep(wait_s / 2)
        deadline = time.monotonic() + 1.5 * wait_s
        while True:
            data, image = capture_screenshot(call)
            if ready is None or ready(image) or time.monotonic() > deadline:
                break
            time.sleep(4.0)
    out.write_bytes(data)
    return image


def camera_panel_stats(image: np.ndarray) -> tuple[float, float, float]:
    """(share of grey scene pixels, share of overlay-coloured pixels, std) in the big camera panel."""
    h, w = image.shape[:2]
    camera_panel = image[int(0.12 * h):int(0.92 * h), : int(0.74 * w)].astype(int)
    b, g, r = camera_panel[..., 0], camera_panel[..., 1], camera_panel[..., 2]
    grey_scene = (np.abs(r - g) < 12) & (np.abs(g - b) < 12) & (g > 40) & (g < 230)
    overlay = ((g > r + 60) & (g > b + 60)) | ((r > 200) & (g > 90) & (g < 200) & (b < 90)) | ((r > g + 80) & (r > b + 80))
    return float(grey_scene.mean()), float(overlay.mean()), float(camera_panel.std())


def shows_camera_with_overlay(image: np.ndarray) -> bool:
    grey, overlay, std = camera_panel_stats(image)
    return grey > 0.5 and std > 20 and overlay > 0.005


def test_web_viewer_shows_the_camera_with_its_overlay(recordings_dir: Path, tmp_path: Path) -> None:
    source = open_source(recordings_dir / "demo_webcam720_careful")
    with Viewer.open("web", out_dir=tmp_path, web_port=free_port(), grpc_port=free_port()) as viewer:
        assert viewer.url is not None and viewer.url.startswith("http://127.0.0.1:")
        run_replay(source, BoardSpec.from_dict(dict(source.info.board)), SessionSettings(),
                   on_outcome=lambda outcome, frame: viewer.log_frame(outcome, frame))
        image = screenshot(viewer.url + "&renderer=webgl", tmp_path / "viewer.png", wait_s=RENDER_WAIT_S,
                           ready=shows_camera_with_overlay)
    grey, overlay, std = camera_panel_stats(image)
    # the camera frame fills the big panel (a blank or still-loading viewer is near-uniform) ...
    assert grey > 0.5 and std > 20, f"see {tmp_path / 'viewer.png'}"
    # ... and the coverage grid, corner markers and pose axes are drawn over it
    assert overlay > 0.005, f"no overlay colours in {tmp_path / 'viewer.png'}"
