"""Browser tests: headless Chromium (Debian's package, driven by Playwright) against the
real stack on simulated hardware. A failing test leaves a screenshot in
``test-artifacts/`` at the checkout's root."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from tests.conftest import simulated_stack

ARTIFACTS = Path(__file__).parents[2] / "test-artifacts"
SPEEDUP = 20


def chromium_path() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    raise RuntimeError("no Chromium on PATH: ./dev test installs Debian's chromium package")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if report.when == "call":
        item.failed_call = report.failed


# Package scope, not session: the stack (its fake lab renders 30 frames a second) stops
# when the browser tests are done instead of taking CPU from every test after them.
@pytest.fixture(scope="package")
def system(tmp_path_factory):
    folder = tmp_path_factory.mktemp("dashboard")
    with simulated_stack(folder, speedup=SPEEDUP, fps=30) as (launcher, settings):
        yield {"url": f"http://127.0.0.1:{settings.gateway.http_port}", "launcher": launcher, "settings": settings}


@pytest.fixture(scope="package")
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=chromium_path(), headless=True)
        yield browser
        browser.close()


@pytest.fixture
def open_page(browser, system, request):
    """Open the dashboard in a window this wide; on failure each page opened is kept as a
    full-page screenshot in test-artifacts/."""
    pages = []

    def open_(width: int = 1500, height: int = 1000):
        page = browser.new_page(viewport={"width": width, "height": height})
        page.set_default_timeout(30_000)
        page.errors = []
        page.on("pageerror", lambda error: page.errors.append(str(error)))
        pages.append(page)
        page.goto(system["url"] + "/")
        page.wait_for_function("document.querySelectorAll('#services li').length >= 5")
        page.wait_for_function("document.getElementById('live').naturalWidth > 0")  # the live frame shown
        return page

    yield open_
    failed = getattr(request.node, "failed_call", False)
    for page in pages:
        if failed:
            ARTIFACTS.mkdir(exist_ok=True)
            width = page.viewport_size["width"] if page.viewport_size else 0
            page.screenshot(path=str(ARTIFACTS / f"{request.node.name}-{width}px.png"), full_page=True)
        page.close()


@pytest.fixture
def page(open_page):
    return open_page()


@pytest.fixture(scope="package")
def lab(system):
    """The REST API as a lab script sees it (semservo.client), to set the scene."""
    from semservo.client import Client

    with Client(system["url"], timeout=30) as client:
        yield client
