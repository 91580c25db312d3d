"""Screenshots of the annotation app for the docs, taken with real Chromium (Playwright, Debian's chromium).

Usage::

    python plugins/annotation_web/scripts/docs_screenshots.py --db feedback.db --campaign NAME --out docs/images

It adds an annotator ``screenshot-annotator`` and an admin ``screenshot-owner`` to the database (use a copy),
starts the app on a free loopback port, and writes ``annotation_signin.png``, ``annotation_guidelines.png``,
``annotation_item.png`` (mid-playback, overlay on) and ``annotation_admin.png``, reduced to 256 colours.
"""

from __future__ import annotations

import argparse
import os
import time

from PIL import Image

from trafficrlhf_sdk.feedback import FeedbackStore

from trafficrlhf_annotation_web.testing import Server

LAUNCH_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
               "--disable-component-update", "--disable-sync"]


def shrink(path: str) -> None:
    """Rewrite a PNG with a 256-colour palette (screenshots are flat UI colours; this keeps them small)."""
    image = Image.open(path).convert("RGB")
    image.quantize(colors=256, method=Image.Quantize.FASTOCTREE).save(path, optimize=True)


def main() -> None:
    """Take the four screenshots."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--db", required=True, help="feedback database (a copy: an annotator and an admin are added)")
    parser.add_argument("--campaign", required=True, help="campaign to show")
    parser.add_argument("--out", required=True, help="directory for the PNGs")
    parser.add_argument("--chromium", default="/usr/bin/chromium", help="the browser binary")
    args = parser.parse_args()
    from playwright.sync_api import sync_playwright

    store = FeedbackStore(args.db)
    names = {a.name for a in store.annotators()}
    token = store.new_token("screenshot-annotator") if "screenshot-annotator" in names else \
        store.add_annotator("screenshot-annotator")[1]
    admin = store.add_admin("screenshot-owner")
    store.close()
    os.makedirs(args.out, exist_ok=True)
    out = {name: os.path.join(args.out, f"annotation_{name}.png") for name in ("signin", "guidelines", "item", "admin")}
    server = Server(args.db).start()
    try:
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=args.chromium, args=LAUNCH_ARGS, headless=True)
            page = browser.new_page(viewport={"width": 1400, "height": 820})
            page.goto(f"{server.url}/?campaign={args.campaign}")
            page.wait_for_selector("#login:not(.hidden)")
            page.screenshot(path=out["signin"])
            page.fill("#token-input", token)
            page.keyboard.press("Enter")
            page.wait_for_selector("#guidelines:not(.hidden)")
            page.screenshot(path=out["guidelines"])
            page.keyboard.press("Enter")
            page.wait_for_function("window.trafficrlhf.item && window.trafficrlhf.mapImage", timeout=30000)
            page.keyboard.press("o")
            page.wait_for_function("window.trafficrlhf.frame > window.trafficrlhf.item.history_steps + 15",
                                   timeout=30000)
            page.keyboard.press("Space")  # pause mid-playback for a steady picture
            time.sleep(0.3)
            page.screenshot(path=out["item"])
            page.goto(f"{server.url}/admin?campaign={args.campaign}")
            page.wait_for_selector("#admin-login:not(.hidden)")
            page.fill("#admin-token", admin)
            page.keyboard.press("Enter")
            page.wait_for_selector("#admin-main:not(.hidden)")
            page.wait_for_function("document.querySelectorAll('#annotators tr').length > 0")
            time.sleep(0.6)  # let the progress bar finish its transition
            page.screenshot(path=out["admin"], full_page=True)
            browser.close()
    finally:
        server.stop()
    for path in out.values():
        shrink(path)
        print(path, os.path.getsize(path), "bytes")


if __name__ == "__main__":
    main()
