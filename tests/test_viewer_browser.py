"""`make demo` starts the live Rerun viewer: it gets the demo's messages and its web page shows the robot.

Real processes (the demo's TLS stack on loopback, the viewer with its own `viewer` certificate) and
the web viewer shipped in the rerun-sdk wheel, rendered by headless Debian chromium (software GL).
"""

from __future__ import annotations

import base64
import json
import re
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rerun", reason="the viz extra (rerun-sdk) is not installed")
pytestmark = pytest.mark.integration

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--no-first-run", "--use-gl=angle",
                  "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
#: Where the README's screenshot of the live view is kept (refreshed by this test when asked).
README_SHOT = Path(__file__).resolve().parent.parent / "docs" / "figures" / "live-viewer.png"


def _stats(log: Path) -> list[dict]:
    return [json.loads(line) for line in log.read_text().splitlines() if line.startswith('{"event": "stats"')]


def _scene(image: np.ndarray) -> np.ndarray:
    """The 3D view's region of the page (inside the layout's left three fifths, clear of the top bar and of where side panels open)."""
    height, width, _ = image.shape
    return image[int(0.10 * height):int(0.90 * height), int(0.20 * width):int(0.58 * width)]


def _coloured(scene: np.ndarray) -> int:
    """Pixels with clear colour (the CBF capsules are blue, the person purple, the binding pairs
    yellow; Rerun's own welcome page and an empty view are grey/white)."""
    return int(((scene.max(axis=2) - scene.min(axis=2)) > 60).sum())


def _screenshot_when_drawn(url: str, path: Path, timeout_s: float = 240.0) -> np.ndarray:
    """Screenshots every 5 s (straight from DevTools: Playwright's own waits for web fonts the
    offline page never gets) until the 3D view shows the scene; the last one."""
    from PIL import Image
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_FLAGS[1:], headless=True)
        page = browser.new_page(viewport={"width": 1280, "height": 720})
        page.goto(url, timeout=60_000)
        cdp = page.context.new_cdp_session(page)
        deadline = time.monotonic() + timeout_s
        while True:
            page.wait_for_timeout(5_000)  # the wasm viewer loads (≈ 20 s), connects and draws
            path.write_bytes(base64.b64decode(cdp.send("Page.captureScreenshot", {"format": "png"})["data"]))
            image = np.asarray(Image.open(path).convert("RGB"), dtype=np.int16)
            if _coloured(_scene(image)) > 2_000 or time.monotonic() > deadline:
                break
        browser.close()
    return image


@pytest.mark.skipif(not Path(CHROMIUM).exists(), reason="Debian chromium is not installed (apt-get install chromium)")
def test_demo_viewer_gets_messages_and_its_web_page_shows_the_robot(spawn, tmp_path: Path) -> None:
    proc = spawn("-m", "safemimic.cli", "demo", "--api-port", "0")
    line = proc.wait_for(lambda text: text.startswith("viewer: http"), 120)
    url = re.search(r"(http://\S+)", line).group(1)
    assert "?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A" in url and url.endswith("%2Fproxy")
    proc.wait_for(lambda text: re.match(r"\s+\d+\.\d +(nominal|active|relaxed|hold) ", text) is not None, 90)
    logs = Path(re.search(r"logs in (\S+)", "".join(proc.output)).group(1))
    assert re.search(r"^\$ safemimic viewer .*--certs ", "".join(proc.output), re.M)  # its own certificate

    image = _screenshot_when_drawn(url, tmp_path / "viewer.png")
    scene = _scene(image)
    assert _coloured(scene) > 2_000, f"no robot/person drawn in the 3D view: {_coloured(scene)} coloured pixels"
    assert scene.std() > 8  # not a uniform region
    if README_SHOT.parent.is_dir() and not README_SHOT.exists():  # rm it to refresh the README's
        shutil.copy(tmp_path / "viewer.png", README_SHOT)

    stats = _stats(logs / "viewer.log")
    assert stats, (logs / "viewer.log").read_text()[-2000:]
    first = stats[0]
    time.sleep(2.5)
    last = _stats(logs / "viewer.log")[-1]
    for topic in ("robot/joint_state", "robot/command", "safety/status", "human/state"):
        assert last["received"].get(topic, 0) > first["received"].get(topic, 0), (topic, first, last)
    for group in ("robot", "person", "joints", "status", "binding"):
        assert last["logged"].get(group, 0) > first["logged"].get(group, 0), (group, first, last)
    assert last["errors"] == {} and last["dropped"] == {}
    assert {"safety", "executor", "perception"} <= set(last["alive"])
    proc.stop()
    assert proc.popen.returncode in (0, -15)
