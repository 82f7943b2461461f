"""`hmdrt watch` in a real browser: headless Chromium (Debian's /usr/bin/chromium, driven by Playwright) on the page
of a watch process attached to a compositor that replays a recorded trace in virtual time slowed to the wall clock.

The page must show the presented frame as it changes, with the gaze marker where the replayed gaze projects, plot
the frames with the newest values in the legends, give each driver's gaze and pose rates, and switch the
compositor's method from its controls; then, watching a real-time run too slow for its VSyncs, mark the repeats on
the frame-time plot. Skipped, with the reason, without Chromium or Playwright. HMDRT_WATCH_SCREENSHOT=PATH saves
the page as it was (docs/img/watch.png was taken so).
"""

from __future__ import annotations

import base64
import io
import os
import shutil

import numpy as np
import pytest
from PIL import Image

from hmdrt.compositor.config import load_config
from hmdrt.compositor.endpoints import request
from hmdrt.testing import Background, Recording, write_config

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
REPEAT = [241, 194, 27]  # a repeat's marker on the frame-time plot (watch.js)
TRACE_HZ = 250.0  # the replayed trace's gaze and pose rates (hmdrt.testing.TRACE)


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


def driver_row(page) -> dict[str, str]:
    """The drivers table's first row, by column heading."""
    return page.evaluate(
        """() => {
            const heads = [...document.querySelectorAll('#drivers thead th')].map((th) => th.textContent);
            const row = document.querySelector('#drivers tbody tr');
            const cells = [...row.querySelectorAll('td')].map((td) => td.textContent);
            return Object.fromEntries(heads.map((head, i) => [head, cells[i]]));
        }"""
    )


def legends(page, chart: str) -> list[dict]:
    """Each series of a plot: its legend's label and value as shown, and its newest value in the plot's data (null
    where it has none), read in one go."""
    return page.evaluate(
        """(id) => {
            const u = window.hmdrtWatch.charts[id];
            const rows = [...document.querySelectorAll(`#${id} .u-legend .u-series`)];
            return rows.map((row, i) => ({
                label: row.querySelector('.u-label').textContent,
                value: row.querySelector('.u-value').textContent,
                newest: u.data[i].findLast((v) => v != null) ?? null,
            }));
        }""",
        chart,
    )


def assert_legends_show_the_newest_values(page, chart: str, labels: list[str]) -> None:
    """The legends of these series of a plot give each its newest value."""
    shown = {series["label"]: series for series in legends(page, chart)}
    for label in labels:
        series = shown[label]
        assert series["newest"] is not None, (chart, series)
        assert float(series["value"].replace(",", "")) == pytest.approx(series["newest"], abs=0.01), (chart, series)


def repeat_marker(page) -> dict | None:
    """A repeat's marker on the frame-time plot, off its edges: its point and the colour drawn there (None: none
    yet)."""
    return page.evaluate(
        """() => {
            const u = window.hmdrtWatch.charts['plot-frame'], [t, , , repeat] = u.data;
            for (let i = repeat.length - 2; i > 0; i--) {
                if (repeat[i] == null) continue;
                const x = Math.round(u.valToPos(t[i], 'x', true)), y = Math.round(u.valToPos(repeat[i], 'y', true));
                const colour = Array.from(u.ctx.getImageData(x, y, 1, 1).data.slice(0, 3));
                return {t: t[i], ms: repeat[i], colour};
            }
            return null;
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

            # without the cursor on a plot, its legend gives each series' newest value; again after the cursor left
            assert_legends_show_the_newest_values(page, "plot-frame", ["frame ms", "period ms"])
            assert_legends_show_the_newest_values(page, "plot-latency", ["gaze-to-photon", "pose-to-photon"])
            page.hover("#plot-frame .u-over")
            page.mouse.move(0, 0)
            assert_legends_show_the_newest_values(page, "plot-frame", ["frame ms", "period ms"])

            # the drivers' table, with the rate of each stream of the 250 Hz trace, and the security counters
            page.wait_for_function(
                "() => ['gaze_hz', 'pose_hz'].every((k) => window.hmdrtWatch.status.drivers.replay?.[k] != null)",
                timeout=WAIT_MS,
            )
            row = driver_row(page)
            assert row["device"] == "replay"
            assert float(row["gaze Hz"]) == pytest.approx(TRACE_HZ, rel=0.1), row
            assert float(row["pose Hz"]) == pytest.approx(TRACE_HZ, rel=0.1), row
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
            comp.close()

            # a real-time run on the same sockets whose renders take longer than a period: the page, still open,
            # plots it afresh and marks its repeats on the period line, the newest in the legend
            sockets = {
                "ingest": comp.ingest.address,
                "telemetry": comp.telemetry.address,
                "control": comp.control.address,
            }
            slow_config = write_config(tmp_path / "slow.toml", eyes="left", pacing={"render_delay_ms": 45}, bus=sockets)
            slow = Recording(load_config(slow_config, duration_s=60), context=context)
            slow_run = Background(slow)
            try:
                page.wait_for_function(
                    "() => window.hmdrtWatch.charts['plot-frame'].data[3].filter((v) => v != null).length >= 3",
                    timeout=WAIT_MS,
                )
                marker = repeat_marker(page)
                assert marker["ms"] == pytest.approx(1000 / 30) and marker["colour"] == REPEAT, marker
                assert legends(page, "plot-frame")[3]["value"].startswith("at "), legends(page, "plot-frame")
            finally:
                slow.stop.set()
                slow_run.join(30)
                slow.close()
            assert not problems, problems
            browser.close()
    finally:
        comp.stop.set()
        run.thread.join(30)
        comp.close()
    assert report["method"] == "full" and report["virtual_time"] is True
