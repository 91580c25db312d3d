"""End to end in a real browser: Debian's chromium, driven by Playwright, against the real server on loopback.

Install the browser with ``scripts/install_browser.sh`` (apt's ``chromium``); the test never downloads one and
skips, saying why, when chromium or the ``playwright`` package is missing.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import time

import pytest

CHROMIUM = os.environ.get("TRAFFICRLHF_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
LAUNCH_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
               "--disable-component-update", "--disable-sync"]


@pytest.fixture()
def page():  # type: ignore[no-untyped-def]
    """A chromium page (1600 x 900)."""
    if not os.path.isfile(CHROMIUM):
        pytest.skip(f"no chromium at {CHROMIUM!r}: run scripts/install_browser.sh (apt-get install chromium)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="the `playwright` Python package is not installed")
    with sync_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=LAUNCH_ARGS, headless=True)
        try:
            tab = browser.new_page(viewport={"width": 1600, "height": 900})
            errors: list[str] = []
            tab.on("pageerror", lambda exc: errors.append(str(exc)))
            yield tab
            assert not errors, f"JavaScript errors on the page: {errors}"
        finally:
            browser.close()


def _labels(db: str) -> list[tuple]:  # type: ignore[type-arg]
    return sqlite3.connect(db).execute(
        "SELECT l.context_id, l.slot, l.candidate, l.permutation FROM labels l JOIN annotators a ON a.id = "
        "l.annotator_id WHERE a.name = 'alice' ORDER BY l.id").fetchall()


def _wait(predicate, timeout_s: float = 10.0) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.05)
    raise AssertionError("condition not met in time")


def test_play_press_key_and_find_the_row(page, server, campaign_db) -> None:  # type: ignore[no-untyped-def]
    db, tokens = campaign_db
    page.goto(f"{server.url}/?token={tokens['alice']}")
    ready = "window.trafficrlhf && window.trafficrlhf.item && window.trafficrlhf.mapImage"
    page.wait_for_function(ready, timeout=15000)
    assert "token=" not in page.url  # the token leaves the address bar
    assert page.locator("canvas").count() == 5
    first = page.evaluate("window.trafficrlhf.item.item")

    # synchronized playback: one clock moves every canvas; Space pauses, arrows scrub
    f0 = page.evaluate("window.trafficrlhf.frame")
    page.wait_for_function(f"window.trafficrlhf.frame >= {f0 + 3}", timeout=5000)
    page.keyboard.press("Space")
    paused = page.evaluate("window.trafficrlhf.frame")
    time.sleep(0.4)
    assert page.evaluate("window.trafficrlhf.frame") == paused and not page.evaluate("window.trafficrlhf.playing")
    page.keyboard.press("ArrowRight")
    assert page.evaluate("window.trafficrlhf.frame") == paused + 1
    assert page.locator("#scrub").input_value() == str(paused + 1)
    # something was drawn: the map and boxes give many colours on every canvas
    colours = page.evaluate("""() => [...document.querySelectorAll('canvas')].map(c => {
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; const seen = new Set();
        for (let i = 0; i < d.length; i += 64) seen.add(d[i] << 16 | d[i + 1] << 8 | d[i + 2]); return seen.size; })""")
    assert min(colours) > 5, colours

    page.keyboard.press("2")  # the most realistic: the candidate shown second
    page.wait_for_function(f"window.trafficrlhf.item && window.trafficrlhf.item.item !== {first}", timeout=10000)
    [(context_id, slot, candidate, permutation)] = _labels(db)
    assert (context_id, slot) == (first, 2) and candidate == eval(permutation)[1]
    assert page.locator("#progress-text").inner_text().startswith("1 / 4")

    second = page.evaluate("window.trafficrlhf.item.item")
    page.reload()  # resume: the same open item comes back
    page.wait_for_function("window.trafficrlhf && window.trafficrlhf.item", timeout=15000)
    assert page.evaluate("window.trafficrlhf.item.item") == second
    page.keyboard.press("0")  # none realistic
    _wait(lambda: len(_labels(db)) == 2)
    assert _labels(db)[1][:3] == (second, 0, None)

    page.wait_for_function(f"window.trafficrlhf.item && window.trafficrlhf.item.item !== {second}", timeout=10000)
    page.keyboard.press("b")  # back: the previous item, in review mode
    page.wait_for_function(f"window.trafficrlhf.item.item === {second}", timeout=10000)
    assert page.evaluate("window.trafficrlhf.item.status") == "labeled"
    assert page.locator("#none").get_attribute("class").split().count("chosen") == 1
    shot = os.environ.get("TRAFFICRLHF_SCREENSHOT")
    if shot:
        page.screenshot(path=shot)
