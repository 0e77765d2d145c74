"""The dashboard in a real headless Chromium (Debian chromium + chromium-driver): it loads, receives
live data over the WebSocket, and draws the trace, the latest window, the trends and both pictures,
each plot with a time axis and y ticks in their units; the page has a favicon."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

from service.pipeline.demo import demo_recording
from tests.servicekit import running_service, service_settings, wait_for

webdriver = pytest.importorskip("selenium.webdriver", reason="needs selenium, a dev extra (deploy/install.sh --dev)")

CHROMEDRIVER = shutil.which("chromedriver")
pytestmark = pytest.mark.skipif(
    CHROMEDRIVER is None or shutil.which("chromium") is None,
    reason="needs Debian's chromium and chromium-driver (deploy/install.sh --dev)",
)

#: Canvases that must show something other than their black background.
CANVASES = ("trace", "window", "trend-frequency", "trend-decay", "trend-settling")
#: The unit of each plot's y ticks.
Y_UNITS = {"trace": "mm", "window": "mm", "trend-frequency": "Hz", "trend-decay": "1/s", "trend-settling": "ms"}
LIT_PIXELS = """
const c = document.getElementById(arguments[0]);
const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
let lit = 0;
for (let i = 0; i < d.length; i += 4) if (d[i] + d[i + 1] + d[i + 2] > 60) lit++;
return lit;
"""


@pytest.fixture()
def browser():  # type: ignore[no-untyped-def]
    options = webdriver.ChromeOptions()
    options.binary_location = shutil.which("chromium")
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu"):
        options.add_argument(arg)
    driver = webdriver.Chrome(options=options, service=webdriver.ChromeService(executable_path=CHROMEDRIVER))
    try:
        yield driver
    finally:
        driver.quit()


def test_the_dashboard_loads_receives_live_data_and_draws(browser, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    cine = demo_recording(tmp_path / "data")
    settings = service_settings(tmp_path / "data", cine.parent, f"file://{cine}?speed=0.25&loop=1")
    with running_service(settings) as base:
        browser.get(base + "/")
        assert browser.title == "meniscope"
        counts = wait_for(
            lambda: (c := browser.execute_script("return window.meniscope"))["windows"] >= 3 and c["traces"] >= 3 and c,
            60,
            "windows and traces over the WebSocket",
        )
        assert counts["draws"] >= 1
        for canvas in CANVASES:
            wait_for(lambda: browser.execute_script(LIT_PIXELS, canvas) > 50, 10, f"a drawing on {canvas}")
        wait_for(lambda: browser.find_element("id", "state").text == "ready", 10, "the ready badge")
        for image in ("frame", "render"):  # the render compiles the ray tracer first: allow for it
            wait_for(
                lambda: browser.execute_script(
                    f"const i = document.getElementById('{image}'); return i.complete && i.naturalWidth === 96"
                ),
                120,
                f"the {image} picture",
            )
        assert browser.find_element("id", "window-caption").text.startswith("#")  # "#<id>: <status> ..."
        # every plot: a time axis with its unit, y ticks each with its unit (no exponents)
        drawn = browser.execute_script("return window.meniscope.axes")
        assert set(drawn) == set(CANVASES)
        for canvas, unit in Y_UNITS.items():
            axis = drawn[canvas]
            assert axis["title"] and len(axis["x"]) >= 2 and 0.0 in map(float, axis["x"]), (canvas, axis)
            assert len(axis["y"]) >= 2 and all(
                re.fullmatch(rf"-?\d+(\.\d+)? {re.escape(unit)}", t) for t in axis["y"]
            ), axis
        assert "mm" in browser.find_element("id", "coefficients").text
        # the favicon: an SVG the page links, served as one
        icon = browser.execute_script("return document.querySelector('link[rel=icon]').href")
        assert icon.endswith("/static/favicon.svg")
        assert (
            browser.execute_script(
                "const r = await fetch(arguments[0]); return r.ok && r.headers.get('content-type')", icon
            )
            == "image/svg+xml"
        )
