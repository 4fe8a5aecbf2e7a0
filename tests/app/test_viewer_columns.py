"""A replay's frames logged as columns (app/viewer_columns.py) read back as frame-by-frame logging's, row for row."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rerun.chunk as rrc

from calibcoach.app.preview import frame_for_log, outcome_for_log
from calibcoach.app.replay import run_replay
from calibcoach.app.session import SessionSettings
from calibcoach.app.viewer import Viewer
from calibcoach.app.viewer_columns import log_frames
from calibcoach.coverage.board import BoardSpec
from calibcoach.drivers.replay import open_source

RECORDING = Path(__file__).resolve().parents[2] / "recordings" / "demo_webcam720_careful"


def rows_by_frame(rrd: Path) -> dict[str, dict[int, dict[str, object]]]:
    """entity -> frame -> {component column: value} (an entity's rows of one frame merged)."""
    found: dict[str, dict[int, dict[str, object]]] = {}
    for chunk in rrc.RrdReader(str(rrd)).stream().to_chunks():
        batch = chunk.to_record_batch()
        if "frame" not in batch.column_names:
            continue
        frames = batch.column("frame").to_pylist()
        columns = [c for c in batch.column_names if ":" in c]
        for i, frame in enumerate(frames):
            row = found.setdefault(chunk.entity_path.lstrip("/"), {}).setdefault(frame, {})
            row.update({c: v for c in columns if (v := batch.column(c)[i].as_py()) is not None})
    return found


@pytest.fixture(scope="module")
def both_ways(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, dict, int]:
    items = []

    def keep(outcome, frame) -> None:  # noqa: ANN001 - the replay's callback signature
        pixelless, jpeg = frame_for_log(frame)
        items.append((outcome_for_log(outcome), pixelless, jpeg, 0.1 * len(items)))

    source = open_source(RECORDING)
    run_replay(source, BoardSpec.from_dict(dict(source.info.board)), SessionSettings(), on_outcome=keep)
    logged = {}
    for way in ("frames", "columns"):
        out = tmp_path_factory.mktemp(way)
        viewer = Viewer.open("none", out_dir=out)
        try:
            if way == "columns":
                log_frames(viewer, items)
            else:
                for outcome, frame, jpeg, _at in items:
                    viewer.log_frame(outcome, frame, jpeg=jpeg)
        finally:
            viewer.close()
        logged[way] = rows_by_frame(out / "session.rrd")
    return logged["frames"], logged["columns"], len(items)


def test_every_frame_has_its_preview_corners_and_decision(both_ways: tuple[dict, dict, int]) -> None:
    frames, columns, n = both_ways
    for entity in ("camera/image", "camera/corners", "log/decisions"):
        assert len(columns[entity]) == len(frames[entity]) == n, entity
    for index, row in frames["camera/image"].items():
        assert columns["camera/image"][index]["EncodedImage:blob"] == row["EncodedImage:blob"]
    for index, row in frames["log/decisions"].items():
        assert columns["log/decisions"][index] == row
    with_corners = 0
    for index, row in frames["camera/corners"].items():
        mine = columns["camera/corners"][index]
        np.testing.assert_array_equal(np.array(mine["Points2D:positions"]).reshape(-1, 2),
                                      np.array(row["Points2D:positions"]).reshape(-1, 2))
        if row["Points2D:positions"]:
            with_corners += 1
            for part in ("colors", "radii", "labels", "show_labels"):
                assert mine[f"Points2D:{part}"] == row[f"Points2D:{part}"], part
    assert 0 < with_corners < n  # frames with and without a board, each its own row


def test_pose_axes_and_target_arrow_match_row_for_row(both_ways: tuple[dict, dict, int]) -> None:
    frames, columns, _n = both_ways
    assert columns["camera/axes"].keys() == frames["camera/axes"].keys()
    posed = 0
    for index, row in frames["camera/axes"].items():
        mine = columns["camera/axes"][index]
        assert mine["LineStrips2D:strips"] == row["LineStrips2D:strips"]
        if row["LineStrips2D:strips"]:
            posed += 1
            assert mine == row
    assert posed > 0
    assert columns["camera/target_arrow"].keys() == frames["camera/target_arrow"].keys()
    arrows = 0
    for index, row in frames["camera/target_arrow"].items():
        mine = columns["camera/target_arrow"][index]
        if "Clear:is_recursive" in row:  # cleared frame by frame, an empty arrow in columns: nothing drawn either way
            assert mine["Arrows2D:vectors"] == []
        else:
            arrows += 1
            assert mine == row
    assert arrows > 0


def test_what_changes_now_and_then_is_logged_alike(both_ways: tuple[dict, dict, int]) -> None:
    frames, columns, _n = both_ways
    for entity in ("camera/coverage", "camera/target", "guidance", "progress/accepted", "progress/coverage_pct",
                   "progress/expected_error_px", "progress/tilt_distance", "progress/processed_fps"):
        assert columns[entity].keys() == frames[entity].keys(), entity
    for entity in ("camera/coverage", "camera/target", "guidance", "progress/accepted"):
        assert columns[entity] == frames[entity], entity
