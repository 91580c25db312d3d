"""End to end in a real browser: Debian's chromium, driven by Playwright, against the real server on loopback.

Install the browser with ``scripts/install_browser.sh`` (apt's ``chromium``); the test never downloads one and
skips, saying why, when chromium or the ``playwright`` package is missing.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import time
import zipfile

import httpx

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


GUIDELINES = """# How to judge

Watch the five futures play, then pick the **most realistic** one.

- blue vehicles are driven by the model, orange ones replay the recording
- press `0` when none is realistic, `E` when the best ones are equally realistic
"""


def test_whole_campaign_by_keyboard(page, server, campaign_db) -> None:  # type: ignore[no-untyped-def]
    """Sign in, read the guidelines, label every item with the keyboard only (the future must play first), then
    check what the export makes of it: N - 1 pairs per choice, N per 'none realistic', none per tie."""
    from trafficrlhf_sdk.feedback import FeedbackStore, export_preferences

    db, tokens = campaign_db
    store = FeedbackStore(db)
    store.update_settings("tiny", playback_required=True, guidelines=GUIDELINES)
    page.goto(server.url + "/")
    page.wait_for_selector("#login:not(.hidden)")
    page.focus("#token-input")
    page.keyboard.type(tokens["alice"])
    page.keyboard.press("Enter")
    page.wait_for_selector("#guidelines:not(.hidden)")
    assert page.locator("#guidelines-body h2").inner_text() == "How to judge"
    assert page.locator("#guidelines-body strong").inner_text() == "most realistic"
    page.keyboard.press("Enter")
    keys = ["2", "0", "e", "4"]
    seen = []
    for n, key in enumerate(keys):
        page.wait_for_function(f"window.trafficrlhf.item && window.trafficrlhf.item.position === {n + 1}",
                               timeout=15000)
        item = page.evaluate("window.trafficrlhf.item.item")
        seen.append(item)
        assert not page.evaluate("window.trafficrlhf.played")
        page.keyboard.press(key)  # too early: refused by the page, nothing stored
        time.sleep(0.3)
        assert len(_labels(db)) == n and page.locator("#toast").inner_text().startswith("Watch the futures")
        page.wait_for_function("window.trafficrlhf.played", timeout=15000)
        assert page.locator("#none").is_enabled()
        page.keyboard.press(key)
        _wait(lambda want=n + 1: len(_labels(db)) == want)
    page.wait_for_selector("#done:not(.hidden)")
    assert page.locator("#progress-text").inner_text().startswith("4 / 4")
    stored = _labels(db)
    assert [row[0] for row in stored] == seen and [row[1] for row in stored] == [2, 0, -1, 4]
    dataset = export_preferences(store, "tiny", val_fraction=0.0)
    per_label = {int(k): int(v) for k, v in zip(*torch_unique(dataset.pair_label))}
    assert sorted(per_label.values()) == [4, 4, 5] and dataset.num_choices == 3  # the tie gives no pair
    assert len(dataset) == 13 and dataset.metadata["num_ties"] == 1
    soft = export_preferences(store, "tiny", val_fraction=0.0, ties="soft")
    assert len(soft) == 13 + 10 and float(soft.labels.sum()) == 13 + 5
    for label_id, slot, candidate in [(r[0], r[1], r[2]) for r in _label_ids(db)]:
        rows = dataset.pairs[dataset.pair_label == label_id]
        if slot > 0:  # the chosen candidate beats each of the other N - 1
            assert set(rows[:, 1].tolist()) == {candidate} and sorted(rows[:, 2].tolist()) == sorted(
                set(range(5)) - {candidate})
        elif slot == 0:  # none realistic: the logged future (index N) beats all N candidates
            assert set(rows[:, 1].tolist()) == {5} and sorted(rows[:, 2].tolist()) == list(range(5))
    store.close()


def torch_unique(values):  # type: ignore[no-untyped-def]
    import torch

    return torch.unique(values, return_counts=True)


def _label_ids(db: str) -> list[tuple]:  # type: ignore[type-arg]
    return sqlite3.connect(db).execute("SELECT id, slot, candidate FROM labels ORDER BY id").fetchall()


def test_admin_page_adds_an_annotator_and_downloads_the_export(page, server, campaign_db) -> None:  # type: ignore[no-untyped-def]
    db, tokens = campaign_db
    page.goto(server.url + "/admin")
    page.wait_for_selector("#admin-login:not(.hidden)")
    page.fill("#admin-token", tokens["admin"])
    page.keyboard.press("Enter")
    page.wait_for_selector("#admin-main:not(.hidden)")
    page.wait_for_function("document.querySelectorAll('#annotators tr').length === 2")
    page.fill("#new-name", "carol")
    page.click("#add-form button")
    page.wait_for_function("document.querySelectorAll('#annotators tr').length === 3")
    token_text = page.locator("#token-out").inner_text()
    assert token_text.startswith("carol: ")
    carol = token_text.split()[1]
    assert sqlite3.connect(db).execute("SELECT COUNT(*) FROM annotators WHERE name = 'carol'").fetchone()[0] == 1
    me = httpx.get(server.url + "/api/me", headers={"Authorization": f"Bearer {carol}"}).json()
    assert me["annotator"] == "carol"
    item = httpx.get(server.url + "/api/campaigns/tiny/next", headers={"Authorization": f"Bearer {carol}"}).json()
    httpx.post(f"{server.url}/api/campaigns/tiny/items/{item['item']}/label", json={"choice": 3},
               headers={"Authorization": f"Bearer {carol}"})
    with page.expect_download() as download:
        page.click("#export-form button")
    path = download.value.path()
    with zipfile.ZipFile(path) as archive:
        assert "tiny/preferences.safetensors" in archive.namelist()
    assert page.locator("#export-out").inner_text() == "4 pairs from 1 choices"
