"""report.html: the page a person opens, from real replays, checked as text and in a real browser."""

from __future__ import annotations

import html
import json
import re
import time
from pathlib import Path

import numpy as np
import pytest

from calibcoach.app.cli import main
from calibcoach.app.outputs.html_report import PICTURE_CAPTIONS, render_report
from calibcoach.app.outputs.report import CAMERA_FILES

from _browser import capture_screenshot, devtools_page, evaluate

_DATA_URI = re.compile(r"data:image/png;base64,[A-Za-z0-9+/=]+")


def external_references(text: str) -> list[str]:
    """Whatever in the page could make a browser fetch something: every src not a data URI, any
    http(s) address, script, stylesheet link, CSS url() or @import (the base64 data itself set aside,
    where 'http' can turn up by chance)."""
    bare = _DATA_URI.sub("data:", text)
    found = [m for m in re.findall(r'src\s*=\s*"([^"]*)"', bare, flags=re.I) if not m.startswith("data:")]
    found += re.findall(r"https?:[^\s\"'<>]*", bare, flags=re.I)
    found += re.findall(r"<script|<link|<iframe|<object|<embed|url\(|@import", bare, flags=re.I)
    return found


@pytest.fixture(scope="module")
def refused(recordings_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("refused")
    assert main(["calibrate", str(recordings_dir / "frontal_webcam720"), "--out", str(out), "--quiet"]) == 3
    return out


def test_a_refused_capture_writes_a_report_saying_refused_and_why(refused: Path) -> None:
    text = (refused / "report.html").read_text(encoding="utf-8")
    payload = json.loads((refused / "calibration.json").read_text(encoding="utf-8"))
    assert not payload["verdict"]["trusted"]
    title = re.search(r"<title>(.*?)</title>", text, flags=re.S).group(1)
    assert "REFUSED" in title and "untrusted" in title
    top = text[text.index("<body>"):text.index('id="numbers"')]  # the verdict comes before any number
    assert "REFUSED" in top and "do not load it as a camera" in top
    for reason in payload["verdict"]["reasons"]:
        assert f"<li>{html.escape(reason)}</li>" in top
    assert external_references(text) == []
    # it is a report, not a camera file: never written as one, and the camera files are still absent
    assert "report.html" not in CAMERA_FILES
    assert not any((refused / name).exists() for name in CAMERA_FILES)
    # every picture written is in it, inlined
    pngs = sorted(p.name for p in refused.glob("*.png"))
    assert pngs and text.count('src="data:image/png;base64,') == len(pngs)
    assert set(pngs) <= set(PICTURE_CAPTIONS)


def test_every_text_is_escaped(refused: Path) -> None:
    payload = json.loads((refused / "calibration.json").read_text(encoding="utf-8"))
    payload["verdict"]["reasons"] = ['<script>alert("x")</script> & <img src="http://example.invalid/x.png">']
    max(payload["frames"], key=lambda f: f["rms_px"])["name"] = "<b>frame</b>"  # listed among the worst
    payload["command_line"] = ["calibcoach", "calibrate", "</pre><script>", "--out", "a&b"]
    payload["dropped_frames"] = [{"frame_index": 3, "reason": "<i>blurred</i>"}]
    text = render_report(payload, [])
    assert "<script" not in text and "<b>frame" not in text and "<i>blurred" not in text
    assert "&lt;script&gt;alert(&quot;x&quot;)&lt;/script&gt; &amp;" in text and "&lt;b&gt;frame&lt;/b&gt;" in text
    assert 'src="http' not in text


@pytest.mark.browser
def test_the_demo_report_in_a_real_browser(recordings_dir: Path, tmp_path: Path) -> None:
    pytest.importorskip("websocket")
    out = tmp_path / "out"
    assert main(["calibrate", str(recordings_dir / "demo_webcam720_careful"), "--out", str(out), "--quiet"]) == 0
    report = out / "report.html"
    text = report.read_text(encoding="utf-8")
    payload = json.loads((out / "calibration.json").read_text(encoding="utf-8"))
    assert external_references(text) == []
    # E two ways (the model's, the holds' scatter: 44 frames in ~17 holds), the larger reported and said so
    sources, E = payload["uncertainty"]["expected_error_sources"], payload["uncertainty"]["expected_error_px"]
    assert sources["holds"] >= 10 and E == pytest.approx(max(sources["from_model_px"], sources["between_holds_px"]), rel=1e-5)
    assert (sources["reported"] == "between holds") == any("scatter between" in r for r in payload["verdict"]["reasons"])
    with devtools_page(tmp_path / "chromium-profile", window=(1300, 1000)) as call:
        call("Page.enable")
        call("Page.navigate", url=report.resolve().as_uri())
        deadline = time.monotonic() + 30
        while evaluate(call, "document.readyState + ':' + [...document.images].every(i => i.complete)") != "complete:true":
            assert time.monotonic() < deadline, "the report never finished loading"
            time.sleep(0.2)
        page = evaluate(call, """JSON.stringify({
            title: document.title,
            verdict: document.getElementById('verdict').innerText,
            numbers: document.getElementById('numbers').innerText,
            frames: document.getElementById('frames').innerText,
            command: document.getElementById('command').innerText,
            images: [...document.images].map(i => ({src: i.src.slice(0, 22), w: i.naturalWidth, h: i.naturalHeight,
                                                    shown: i.getBoundingClientRect().width}))})""")
        _, image = capture_screenshot(call)
    page = json.loads(page)
    grade = payload["verdict"]["grade"].upper()
    assert page["title"] == f"calibcoach report: {grade}, TRUSTED"
    assert f"{grade}: trusted" in page["verdict"]
    assert all(reason in page["verdict"] for reason in payload["verdict"]["reasons"])
    K = payload["camera_matrix"]
    for number in (f"{K[0][0]:.4f}", f"{K[1][1]:.4f}", f"{payload['rms_px']:.3f} px", "k1", "k3",
                   f"{payload['frames_used']} / 120"):
        assert number in page["numbers"], number
    assert f"{sources['from_model_px']:.3f} / {sources['between_holds_px']:.3f} px" in page["numbers"]  # E both ways
    worst = max(payload["frames"], key=lambda f: f["rms_px"])
    assert worst["name"] in page["frames"]  # the worst frame named
    assert page["command"].startswith("calibcoach calibrate ") and "demo_webcam720_careful" in page["command"]
    names = sorted(p.name for p in out.glob("*.png"))
    assert len(page["images"]) == len(names) == 8  # coverage, tilt x2, residuals on the image and the board, per-frame, uncertainty, check image
    for img in page["images"]:
        assert img["src"] == "data:image/png;base64,"
        assert img["w"] >= 1000 and img["h"] > 100 and img["shown"] > 0, img  # decoded (every picture is >= 1000 px wide)
    # the first screen is a page, not a blank: text and the verdict's green box
    assert image.std() > 20
    b, g, r = (image[..., c].astype(int) for c in range(3))
    assert ((g > r + 40) & (g > b + 20)).mean() > 0.001, "no green verdict box on the first screen"
    assert (np.abs(image.astype(int) - 250).sum(axis=2) > 200).mean() > 0.02, "hardly any ink on the first screen"
