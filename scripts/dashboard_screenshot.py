"""Regenerate docs/dashboard.png: the dashboard after a converged run, in headless
Chromium, on the simulated lab at 20x speed.

    .venv/bin/python scripts/dashboard_screenshot.py
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from playwright.sync_api import sync_playwright

from semservo.config import Settings
from semservo.launcher import Launcher

OUT = Path(__file__).parents[1] / "docs" / "dashboard.png"


def main() -> int:
    folder = Path(tempfile.mkdtemp(prefix="semservo-screenshot-"))
    os.environ.update(SEMSERVO_FAKELAB__SPEEDUP="20", SEMSERVO_STAGE__MAX_RATE_V_PER_S="4000",
                      SEMSERVO_IMAGESERVER__FPS="30", SEMSERVO_CONTROLLER__RUNS_DIR=str(folder / "runs"),
                      SEMSERVO_GATEWAY__DATABASE=str(folder / "runs" / "semservo.sqlite"))
    settings = Settings()
    launcher = Launcher(settings, out=(folder / "services.log").open("w"))
    launcher.start(timeout_s=90)
    try:
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=shutil.which("chromium"), headless=True)
            page = browser.new_page(viewport={"width": 1500, "height": 1000})
            page.goto(f"http://127.0.0.1:{settings.gateway.http_port}/")
            page.wait_for_function("document.getElementById('live').naturalWidth > 0")
            page.click("#teach-live")
            page.wait_for_function("document.getElementById('reference').naturalWidth > 0")
            page.fill("#jog-step", "4")
            page.click("#jog-x-plus")
            page.click("#jog-y-minus")
            page.wait_for_timeout(800)
            page.click("#start")
            page.wait_for_function("document.getElementById('state').textContent === 'converged'", timeout=120_000)
            page.wait_for_timeout(2000)
            page.screenshot(path=str(OUT))
            browser.close()
    finally:
        launcher.stop()
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
