"""The gateway's security rules on a real uvicorn: loopback by default, a token required
anywhere else, checked on every state-changing endpoint and never logged."""

from __future__ import annotations

import subprocess
import sys
import time

import httpx
import pytest

from semservo.client import Client, SemservoError

pytestmark = pytest.mark.integration

TOKEN = "correct-horse-battery-staple"


def gateway(env_extra: dict, monkeypatch, tmp_path) -> subprocess.Popen:
    for key, value in env_extra.items():
        monkeypatch.setenv(key, value)
    monkeypatch.setenv("SEMSERVO_GATEWAY__DATABASE", str(tmp_path / "runs.sqlite"))
    return subprocess.Popen([sys.executable, "-m", "semservo", "service", "gateway"], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def wait_http(url: str, timeout_s: float = 20) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            httpx.get(url + "/openapi.json", timeout=1)
            return
        except httpx.TransportError:
            time.sleep(0.1)
    raise AssertionError("the gateway did not start serving")


def test_any_address_but_loopback_without_a_token_is_refused(ports, monkeypatch, tmp_path):
    process = gateway({"SEMSERVO_GATEWAY__HTTP_HOST": "0.0.0.0"}, monkeypatch, tmp_path)
    output, _ = process.communicate(timeout=30)
    assert process.returncode == 2
    assert "without an API token" in output


def test_a_token_guards_every_state_changing_endpoint(ports, monkeypatch, tmp_path):
    process = gateway({"SEMSERVO_GATEWAY__HTTP_HOST": "0.0.0.0", "SEMSERVO_GATEWAY__API_TOKEN": TOKEN},
                      monkeypatch, tmp_path)
    url = f"http://127.0.0.1:{ports['gateway_http']}"
    try:
        wait_http(url)
        for method, path in (("POST", "/teach"), ("POST", "/teach/polygon"), ("POST", "/stage/move"),
                             ("POST", "/start"), ("POST", "/stop")):
            for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": f"Basic {TOKEN}"}):
                response = httpx.request(method, url + path, headers=headers, json={})
                assert response.status_code == 401, (path, headers)
                assert response.json()["error"]["code"] == "unauthorized"
        # Reading needs no token; with it, a state-changing call gets past the check
        # (here to the services, which are not running: named, as a 503).
        assert httpx.get(url + "/runs").status_code == 200
        with Client(url, token=TOKEN) as lab:
            with pytest.raises(SemservoError) as refused:
                lab.stop("checking the token")
            assert refused.value.status == 503 and refused.value.code == "stop_failed"
            assert next(lab.events())["kind"] == "hello"
        # The live events without the token: the clients' own error, as REST's 401 (a
        # script got websockets' ConnectionClosedError or InvalidStatus).
        with Client(url) as lab:
            with pytest.raises(SemservoError) as refused:
                next(lab.events())
            assert refused.value.code == "unauthorized" and "give the API token" in refused.value.message
        with Client(f"http://127.0.0.1:{ports['gateway_http'] + 1}") as nobody:  # no gateway there
            with pytest.raises(SemservoError) as refused:
                next(nobody.events())
            assert refused.value.code == "unreachable" and "is the system up" in refused.value.message
    finally:
        process.terminate()
        output, _ = process.communicate(timeout=15)
    assert TOKEN not in output  # never logged
