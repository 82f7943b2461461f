"""`hmdrt watch` in a real browser: headless Chromium (Debian's /usr/bin/chromium, driven by Playwright) on the page
of a watch process attached to a compositor that replays a recorded trace in virtual time slowed to the wall clock.

The page must show the presented frame as it changes, with the gaze marker where the replayed gaze projects, plot
the frames, and switch the compositor's method from its controls. Skipped, with the reason, without Chromium or
Playwright. HMDRT_WATCH_SCREENSHOT=PATH saves the page as it was (docs/img/watch.png was taken so).
"""

from __future__ import annotations

import base64
import io
import os
import shutil

import numpy as np
import pytest
from PIL import Image

from hmdrt.compositor.endpoints import request
from hmdrt.testing import Background, write_config

from .helpers import wait_for
from .watching import expected_gaze, paced_compositor, watch_process

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
playwright = pytest.importorskip("playwright.sync_api", reason="Playwright for Python is not installed")
pytestmark = pytest.mark.skipif(
    not shutil.which(CHROMIUM), reason=f"no Chromium at {CHROMIUM} (apt-get install -y chromium)"
)
WAIT_MS = 20_000
MARKER = [0, 255, 0]  # the gaze point's colour on the page (watch.js)


def canvas_image(page) -> np.ndarray:
    """The preview canvas as the browser drew it, RGB."""
    url = page.evaluate("document.getElementById('preview').toDataURL('image/png')")
    with Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))) as image:
        return np.asarray(image.convert("RGB"))


def marks(page) -> dict:
    """The newest preview's header and, at each eye's gaze point on the canvas, the colour drawn there: read in one
    go, so that both are of the same preview."""
    return page.evaluate(
        """() => {
            const header = window.hmdrtWatch.lastPreview, canvas = document.getElementById('preview');
            const k = canvas.width / header.width, ctx = canvas.getContext('2d');
            const colours = header.eyes.map((eye) => Array.from(
                ctx.getImageData(Math.round(eye.gaze[0] * k), Math.round(eye.gaze[1] * k), 1, 1).data.slice(0, 3)));
            return {header, colours};
        }"""
    )


def test_the_page_shows_the_run_live_and_switches_the_method(tmp_path, context):
    config = write_config(
        tmp_path / "watch.toml",
        display={"resolution": "160x180"},
        output={"snapshot_dir": "snaps"},
        controller={"kind": "hold-budget"},
    )
    comp = paced_compositor(config, context)
    run = Background(comp)
    try:
        with (
            watch_process("--control", comp.control.address) as (_, url, token, read_only_url),
            playwright.sync_playwright() as driver,
        ):
            browser = driver.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            problems = []
            page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
            page.on("pageerror", lambda e: problems.append(str(e)))
            page.goto(url)
            assert "token" not in page.url  # taken out of the address bar, kept in the tab's session

            # a preview arrives and changes
            page.wait_for_function("() => window.hmdrtWatch.previews >= 1", timeout=WAIT_MS)
            first = canvas_image(page)
            assert first.std() > 5  # a scene, not a blank canvas
            page.wait_for_function("() => window.hmdrtWatch.previews >= 4", timeout=WAIT_MS)
            assert not np.array_equal(canvas_image(page), first)

            # the gaze marker sits where the replayed gaze projects, and moves with it
            seen = []
            for _ in range(60):
                seen.append(marks(page))
                positions = {tuple(round(v) for v in s["header"]["eyes"][0]["gaze"]) for s in seen}
                if len(positions) >= 3:
                    break
                page.wait_for_timeout(200)
            assert len(positions) >= 3, positions
            for s in seen:
                header = s["header"]
                assert header["gaze_known"] and header["method"] == "rrm" and header["fovea_deg"] > 0
                expected = expected_gaze(comp, header)
                for eye, want, colour in zip(header["eyes"], expected, s["colours"], strict=True):
                    assert eye["gaze"] == pytest.approx(want, abs=1e-6)
                    if 0 <= want[0] - eye["x0"] < eye["width"] and 0 <= want[1] < header["height"]:
                        assert colour == MARKER, (header, s["colours"])

            # the plots have points: frame time and latency of every VSync, the controller's level
            page.wait_for_function("() => window.hmdrtWatch.frames >= 30", timeout=WAIT_MS)
            points = page.evaluate(
                """() => Object.fromEntries(Object.entries(window.hmdrtWatch.charts).map(
                    ([id, chart]) => [id, chart.data.map((s) => s.filter((v) => v != null).length)]))"""
            )
            assert points["plot-frame"][0] >= 30 and points["plot-frame"][1] >= 10, points
            assert points["plot-latency"][1] >= 10 and points["plot-latency"][2] >= 10, points
            # each eye's gaze error at photon time, put at its own VSync, and the foveal radius
            assert all(n >= 10 for n in points["plot-gaze-error"][1:]), points
            page.wait_for_function("() => document.getElementById('summary').textContent.includes('gaze error p95')")
            # the controller's level comes with the status, once a second: wait for ten of its points
            page.wait_for_function(
                "() => window.hmdrtWatch.charts['plot-controller'].data[1].filter((v) => v != null).length >= 10",
                timeout=WAIT_MS,
            )

            # the drivers' table and the security counters
            page.wait_for_function("() => document.querySelectorAll('#drivers tbody tr').length >= 1", timeout=WAIT_MS)
            assert page.inner_text("#drivers tbody tr td") == "replay"
            assert "watch: refused" in page.inner_text("#security")

            if os.environ.get("HMDRT_WATCH_SCREENSHOT"):  # with 10 s of plots
                page.wait_for_function("() => window.hmdrtWatch.frames >= 300", timeout=WAIT_MS)
                page.screenshot(path=os.environ["HMDRT_WATCH_SCREENSHOT"], full_page=True)

            # the method switch from the page reaches the compositor
            assert page.is_enabled("#apply")
            page.select_option("#method", "full")
            page.click("#apply")
            page.wait_for_function("() => window.hmdrtWatch.replies.length >= 1", timeout=WAIT_MS)
            assert page.evaluate("window.hmdrtWatch.replies[0]") == {
                "type": "reply",
                "id": 1,
                "ok": True,
                "method": "full",
            }
            assert wait_for(lambda: request(comp.control.address, {"cmd": "status"})["method"] == "full", 30)
            page.wait_for_function("() => window.hmdrtWatch.lastPreview.method === 'full'", timeout=WAIT_MS)
            page.wait_for_function("() => document.getElementById('run').textContent.startsWith('full on whitted')")

            # a page without the token shows the run and cannot change it
            viewer = browser.new_page()
            viewer.goto(read_only_url)
            viewer.wait_for_function("() => window.hmdrtWatch.previews >= 1", timeout=WAIT_MS)
            assert viewer.is_disabled("#apply") and viewer.is_disabled("#shutdown")
            assert "read-only" in viewer.inner_text("#controls-why")

            # shutdown from the page ends the run
            page.once("dialog", lambda dialog: dialog.accept())
            page.click("#shutdown")
            report, _ = run.join(30)
            assert not problems, problems
            browser.close()
    finally:
        comp.stop.set()
        run.thread.join(30)
        comp.close()
    assert report["method"] == "full" and report["virtual_time"] is True
