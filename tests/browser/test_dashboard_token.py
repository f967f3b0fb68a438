"""The dashboard with an API token configured: state-changing controls are refused
without it (said in words) and pass with it."""

from __future__ import annotations

import subprocess
import sys

import pytest
from playwright.sync_api import expect

from tests.conftest import choose_ports
from tests.integration.test_gateway_security import wait_http

pytestmark = pytest.mark.integration

TOKEN = "dashboard-token-123"


def test_controls_need_the_token_typed_into_the_header(browser, tmp_path):
    with pytest.MonkeyPatch.context() as env:
        ports = choose_ports(env)  # nothing else runs on these: the services are down
        env.setenv("SEMSERVO_GATEWAY__API_TOKEN", TOKEN)
        env.setenv("SEMSERVO_GATEWAY__DATABASE", str(tmp_path / "runs.sqlite"))
        gateway = subprocess.Popen([sys.executable, "-m", "semservo", "service", "gateway"],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    url = f"http://127.0.0.1:{ports['gateway_http']}"
    page = browser.new_page()
    try:
        wait_http(url)
        page.goto(url + "/")
        # The live events are refused without the token: said, not an empty plot forever.
        expect(page.locator("#message-text")).to_contain_text("live updates (plots, iterations) need the API token")
        page.click("#stop")
        expect(page.locator("#message-text")).to_contain_text("bearer token")
        page.fill("#token", TOKEN)
        page.dispatch_event("#token", "change")
        page.click("#stop")
        # Past the token check: the services are not running, and the dashboard says so.
        expect(page.locator("#message-text")).to_contain_text("neither the stage nor the controller answered")
        assert page.evaluate("localStorage.getItem('semservo-token')") == TOKEN
    finally:
        page.close()
        gateway.terminate()
        gateway.wait(timeout=15)
