"""Headless chromium driven over the DevTools protocol, for the tests that look at a real page.

`devtools_page(profile_dir)` starts chromium with remote debugging on a free port and yields a
`call(method, **params)` that sends one DevTools command to the first tab and returns its reply;
`evaluate(call, expression)` runs a JavaScript expression in the page and returns its value.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import socket
import subprocess
import time
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import pytest

Call = Callable[..., dict]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def chromium_path() -> str:
    path = shutil.which("chromium")
    if path is None:
        if os.environ.get("CI"):
            pytest.fail("chromium is missing on CI: .ci/run installs Debian's chromium package")
        pytest.skip("chromium is not installed (apt-get install chromium); CI installs it")
    return path


_STARTS = 3  # chromium's first start on a busy host has failed to open its DevTools port (twice in one CI run)
_START_WAIT_S = 30.0


def _started_chromium(profile: Path, window: tuple[int, int]) -> tuple[subprocess.Popen, list[dict]]:
    """A headless chromium whose DevTools endpoint answers, and its tabs; started again (new port)
    when one does not come up, and on the last failure its exit code and log's end are the message."""
    log_path = profile.parent / f"{profile.name}-chromium.log"
    for attempt in range(_STARTS):
        port = free_port()
        user_data = profile if attempt == 0 else profile.with_name(f"{profile.name}-{attempt}")  # a killed start's lock stays behind
        flags = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 f"--user-data-dir={user_data}", f"--remote-debugging-port={port}", "--remote-allow-origins=*",
                 f"--window-size={window[0]},{window[1]}", "about:blank"]  # newer chromium refuses DevTools websockets from other origins
        with open(log_path, "wb") as log:
            browser = subprocess.Popen([chromium_path(), *flags], stdout=subprocess.DEVNULL, stderr=log)
        deadline = time.monotonic() + _START_WAIT_S
        while time.monotonic() < deadline and browser.poll() is None:
            try:
                tabs = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json", timeout=1))
            except OSError:
                tabs = []
            if any(t.get("type") == "page" for t in tabs):
                return browser, tabs
            time.sleep(0.1)
        browser.kill()
        browser.wait()
        if attempt == _STARTS - 1:
            tail = log_path.read_text(errors="replace").strip().splitlines()[-5:]
            pytest.fail(f"chromium's DevTools endpoint never came up in {_STARTS} starts (last exit code "
                        f"{browser.returncode}); its log ends: " + " | ".join(tail))
    raise AssertionError("unreachable")


@contextmanager
def devtools_page(profile: Path, *, window: tuple[int, int] = (1600, 1000)) -> Iterator[Call]:
    """A headless chromium with one blank tab; yields `call(method, **params) -> reply`."""
    import websocket

    browser, tabs = _started_chromium(profile, window)
    try:
        page = next(t for t in tabs if t["type"] == "page")
        ws = websocket.create_connection(page["webSocketDebuggerUrl"], timeout=60)
        counter = iter(range(1, 100_000))

        def call(method: str, **params: object) -> dict:
            call_id = next(counter)
            ws.send(json.dumps({"id": call_id, "method": method, "params": params}))
            while True:
                message = json.loads(ws.recv())
                if message.get("id") == call_id:
                    return message

        try:
            yield call
        finally:
            ws.close()
    finally:
        browser.kill()
        browser.wait()


def evaluate(call: Call, expression: str) -> object:
    """The value of a JavaScript expression in the page (JSON-serialisable results only)."""
    reply = call("Runtime.evaluate", expression=expression, returnByValue=True)
    assert "exceptionDetails" not in reply.get("result", {}), reply
    return reply["result"]["result"].get("value")


def capture_screenshot(call: Call, **params: object) -> tuple[bytes, np.ndarray]:
    """(PNG bytes, BGR image) of the page as it is now."""
    data = base64.b64decode(call("Page.captureScreenshot", format="png", **params)["result"]["data"])
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None
    return data, image
