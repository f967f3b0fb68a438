"""Regenerate docs/dashboard.png: the dashboard after a converged run, with a stored
target and the run's detail open, in headless Chromium, on the simulated lab at 20x
speed (fresh ports: it never touches a system already running on the default ones).

    .venv/bin/python scripts/dashboard_screenshot.py [--width 1500] [--out docs/dashboard.png]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path

from playwright.sync_api import sync_playwright

from semservo.launcher import simulated_system

OUT = Path(__file__).parents[1] / "docs" / "dashboard.png"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=1500, help="window width, px")
    parser.add_argument("--height", type=int, default=1150, help="window height, px")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="semservo-screenshot-"))
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    with simulated_system(folder, speedup=20, fps=30) as (_launcher, settings), sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=chromium, headless=True)
        page = browser.new_page(viewport={"width": args.width, "height": args.height})
        page.goto(f"http://127.0.0.1:{settings.gateway.http_port}/")
        page.wait_for_function("document.getElementById('live').naturalWidth > 0")
        page.click("#teach-live")
        page.wait_for_function("document.getElementById('reference').naturalWidth > 0")
        page.fill("#target-name", "bond pad 3")
        page.fill("#target-note", "left of the crack, before the anneal")
        page.click("#target-save-button")
        page.wait_for_selector("#targets li img")
        page.fill("#jog-step", "4")
        page.click("#jog-x-plus")
        page.click("#jog-y-minus")
        page.wait_for_timeout(800)
        page.click("#start")
        page.wait_for_function("document.getElementById('state').textContent === 'converged'", timeout=120_000)
        page.wait_for_timeout(1500)
        page.click("#refresh-runs")
        page.click("#runs tr")
        page.wait_for_function("document.getElementById('detail-report').naturalWidth > 0")
        page.evaluate("window.scrollTo(0, 0)")
        page.wait_for_timeout(500)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(args.out))
        browser.close()
    shutil.rmtree(folder, ignore_errors=True)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
