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
def page(browser, system, request):
    page = browser.new_page(viewport={"width": 1500, "height": 1000})
    page.set_default_timeout(30_000)
    page.errors = []
    page.on("pageerror", lambda error: page.errors.append(str(error)))
    page.goto(system["url"] + "/")
    page.wait_for_function("document.querySelectorAll('#services li').length >= 5")
    yield page
    if getattr(request.node, "failed_call", False):
        ARTIFACTS.mkdir(exist_ok=True)
        page.screenshot(path=str(ARTIFACTS / f"{request.node.name}.png"), full_page=True)
    page.close()
