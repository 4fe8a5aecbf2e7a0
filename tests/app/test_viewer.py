"""The Rerun viewer, with real rerun: a replayed session saved to .rrd, checked by rerun's own tools.

No mocks: the .rrd must pass `rerun rrd verify` and read back with rerun's chunk reader, so a
change in rerun's API or in our entity paths shows up here, not in front of a user.
"""

from __future__ import annotations

import socket
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
import rerun.chunk as rrc

from calibcoach.app.replay import run_replay
from calibcoach.app.session import SessionSettings
from calibcoach.app.viewer import Viewer, ViewerError
from calibcoach.coverage.board import BoardSpec
from calibcoach.drivers.replay import open_source

RECORDING = Path(__file__).resolve().parents[2] / "recordings" / "demo_webcam720_careful"
REQUIRED_ENTITIES = ("camera/image", "camera/corners", "camera/axes", "camera/target", "camera/target_arrow", "guidance",
                     "progress/expected_error_px", "progress/error_target_px", "progress/coverage_pct", "progress/tilt_distance", "progress/processed_fps",
                     "report/verdict", "report/per_frame_rms_px")


@dataclass
class Run:
    rrd: Path
    frames_logged: int
    grade: str


def rerun_cli() -> list[str]:
    beside = Path(sys.executable).with_name("rerun")
    return [str(beside)] if beside.exists() else [sys.executable, "-m", "rerun"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def chunks_by_entity(rrd: Path) -> dict[str, list[rrc.Chunk]]:
    found: dict[str, list[rrc.Chunk]] = {}
    for chunk in rrc.RrdReader(str(rrd)).stream().to_chunks():
        found.setdefault(chunk.entity_path.lstrip("/"), []).append(chunk)
    return found


@pytest.fixture(scope="module")
def replayed(tmp_path_factory: pytest.TempPathFactory) -> Run:
    out = tmp_path_factory.mktemp("viewer")
    viewer = Viewer.open("none", out_dir=out)
    logged: list[int] = []

    def log(outcome, frame) -> None:  # noqa: ANN001 - the replay's callback signature
        viewer.log_frame(outcome, frame)
        logged.append(frame.index)

    try:
        source = open_source(RECORDING)
        session, _stats = run_replay(source, BoardSpec.from_dict(dict(source.info.board)), SessionSettings(),
                                     on_outcome=log)
        result = session.finish()
        # one PNG as the report would have written it (reused as is); the others are rendered here
        cv2.imwrite(str(out / "coverage.png"), np.full((40, 60, 3), 255, np.uint8))
        viewer.log_result(result, out)
    finally:
        viewer.close()
    viewer.close()  # idempotent
    return Run(viewer.rrd_path, len(logged), result.verdict.grade)


def test_saved_recording_passes_rerun_verify(replayed: Run) -> None:
    assert replayed.rrd == replayed.rrd.parent / "session.rrd"
    done = subprocess.run([*rerun_cli(), "rrd", "verify", str(replayed.rrd)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr


def test_saved_recording_holds_the_live_and_report_entities(replayed: Run) -> None:
    entities = chunks_by_entity(replayed.rrd)
    missing = [e for e in REQUIRED_ENTITIES if e not in entities]
    assert not missing, f"missing {missing}; found {sorted(entities)}"
    # every frame's preview is logged (it is the live view), on the frame timeline
    images = entities["camera/image"]
    assert sum(c.num_rows for c in images) == replayed.frames_logged
    assert all("frame" in c.timeline_names and "capture_time" in c.timeline_names for c in images)
    # the verdict is the Markdown a person reads first
    texts = [t for c in entities["report/verdict"] for t in c.to_record_batch().column("TextDocument:text").to_pylist()]
    assert replayed.grade.upper() in texts[-1][0]
    # report pictures: the report's own PNG reused, the missing ones rendered (PNG either way)
    for entity in ("report/coverage", "report/residual_map", "report/uncertainty", "report/per_frame_errors"):
        media = entities[entity][0].to_record_batch().column("EncodedImage:media_type").to_pylist()[0]
        assert media == ["image/png"], entity
    assert "report/residuals" in entities
    # coverage is logged only when a frame was kept, not every frame
    assert 0 < sum(c.num_rows for c in entities["camera/coverage"]) < replayed.frames_logged
    # the ghost board: an outline along the board's edges (4 x 12 points, closed) labelled with its sentence
    ghost = [b for c in entities["camera/target"] for b in [c.to_record_batch()] if "LineStrips2D:strips" in b.column_names]
    strips = [s for b in ghost for s in b.column("LineStrips2D:strips").to_pylist() if s]
    assert strips and all(len(s[0]) == 49 for s in strips)
    labels = [t for b in ghost for t in b.column("LineStrips2D:labels").to_pylist() if t]
    assert labels and all(str(t[0]).startswith("Board ") for t in labels)


def test_saved_recording_carries_the_blueprint(replayed: Run) -> None:
    assert len(rrc.RrdReader(str(replayed.rrd)).blueprints()) == 1


def test_web_mode_serves_on_localhost_only(tmp_path: Path) -> None:
    web_port, grpc_port = free_port(), free_port()
    viewer = Viewer.open("web", out_dir=tmp_path, web_port=web_port, grpc_port=grpc_port)
    try:
        assert viewer.url is not None and viewer.url.startswith(f"http://127.0.0.1:{web_port}/")
        assert f"127.0.0.1%3A{grpc_port}" in viewer.url
        with socket.create_connection(("127.0.0.1", web_port), timeout=5):
            pass
    finally:
        viewer.close()
    viewer.close()
    assert subprocess.run([*rerun_cli(), "rrd", "verify", str(tmp_path / "session.rrd")],
                          capture_output=True, timeout=60).returncode == 0


def test_unknown_mode_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ViewerError, match="unknown viewer mode"):
        Viewer.open("browser", out_dir=tmp_path)


def test_native_mode_without_a_display_saves_only(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    viewer = Viewer.open("native", out_dir=tmp_path, grpc_port=free_port())
    viewer.close()
    if sys.platform.startswith("linux"):
        assert viewer.notice is not None and "no display" in viewer.notice
    assert viewer.url is None
    assert subprocess.run([*rerun_cli(), "rrd", "verify", str(tmp_path / "session.rrd")],
                          capture_output=True, timeout=60).returncode == 0
