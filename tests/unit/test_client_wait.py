"""`Client.wait(stop_on_timeout=True)` leaves no run behind and stops no other: the
client's logic against a gateway stand-in (httpx's transport), the paths a live stack
cannot provoke on demand (a gateway answering 503 while it restarts, Ctrl-C mid-wait, a
gateway gone at the deadline). The live paths are in tests/faults/test_requests.py."""

from __future__ import annotations

import asyncio
import json

import httpx
import pytest

from semservo import client as client_module
from semservo.client import AsyncClient, Client, WaitTimeout

RUN = "20261127-120000-abcdef"


class Gateway:
    """Answers /runs/{id}, /status and /stop from a script of what happens."""

    def __init__(self, *, failing_polls: int = 0, finished_after: int | None = None, status: int = 200,
                 servoing: str | None = RUN, interrupt_at: int | None = None):
        self.failing_polls, self.finished_after, self.status = failing_polls, finished_after, status
        self.servoing, self.interrupt_at = servoing, interrupt_at
        self.polls, self.stops = 0, []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        path = request.url.path
        if path == f"/runs/{RUN}":
            self.polls += 1
            if self.interrupt_at is not None and self.polls >= self.interrupt_at:
                raise KeyboardInterrupt
            if self.polls <= self.failing_polls:
                return httpx.Response(503, json={"error": {"code": "gateway_restarting", "message": "restarting",
                                                           "field": None}})
            finished = self.finished_after is not None and self.polls > self.finished_after
            return httpx.Response(200, json=record("converged" if finished else "servoing"))
        if self.status != 200:
            return httpx.Response(self.status, json={"error": {"code": "down", "message": "down", "field": None}})
        if path == "/status":
            return httpx.Response(200, json=status(self.servoing))
        if path == "/stop":
            self.stops.append(json.loads(request.content)["reason"])
            return httpx.Response(200, json={"state": "stopped", "stage_stopped": True})
        return httpx.Response(404, json={"error": {"code": "not_found", "message": path, "field": None}})


def record(state: str) -> dict:
    return {"id": RUN, "reference_id": "ref", "started_at_ns": 1, "finished_at_ns": None, "state": state,
            "reason": "", "iterations": 3, "final_error_px": None, "truth": None, "settings": None,
            "reference": None, "outcome": None, "trajectory": [], "stage_commands": []}


def status(run_id: str | None) -> dict:
    return {"state": "servoing" if run_id else "idle", "run_id": run_id, "iteration": 3, "error_px": None,
            "error_um": None, "cost": None, "last_latency_ms": None, "latency_p50_ms": None, "latency_p99_ms": None,
            "estimation_ms": None, "frame_rate": 2.0, "latest_frame_seq": 7, "reference": None, "stage": {},
            "services": {}, "down": []}


def client_on(gateway: Gateway) -> Client:
    lab = Client("http://gateway")
    lab.http = httpx.Client(base_url="http://gateway", transport=httpx.MockTransport(gateway))
    return lab


def test_a_gateway_restarting_mid_wait_is_asked_again():
    gateway = Gateway(failing_polls=3, finished_after=4)
    assert client_on(gateway).wait(RUN, timeout=5, poll_s=0.01).state == "converged"
    assert gateway.polls == 5 and not gateway.stops


def test_giving_up_stops_the_run_it_waited_for():
    gateway = Gateway()
    with pytest.raises(WaitTimeout, match="it was stopped"):
        client_on(gateway).wait(RUN, timeout=0.05, poll_s=0.01, stop_on_timeout=True)
    assert len(gateway.stops) == 1 and RUN in gateway.stops[0]


def test_giving_up_on_another_scripts_run_stops_nothing():
    gateway = Gateway(servoing="20261127-130000-fedcba")
    with pytest.raises(WaitTimeout, match="not servoing, so not stopped"):
        client_on(gateway).wait(RUN, timeout=0.05, poll_s=0.01, stop_on_timeout=True)
    assert not gateway.stops


def test_ctrl_c_mid_wait_stops_the_run():
    gateway = Gateway(interrupt_at=3)
    with pytest.raises(KeyboardInterrupt):
        client_on(gateway).wait(RUN, timeout=5, poll_s=0.01, stop_on_timeout=True)
    assert len(gateway.stops) == 1 and "ended in an error" in gateway.stops[0]


def test_a_gateway_gone_at_the_deadline_is_said_not_hidden(monkeypatch):
    monkeypatch.setattr(client_module, "STOP_TRIES_S", 0.1)
    gateway = Gateway(status=503)
    with pytest.raises(WaitTimeout, match="could NOT be stopped"):
        client_on(gateway).wait(RUN, timeout=0.05, poll_s=0.01, stop_on_timeout=True)


def test_the_asyncio_client_gives_up_the_same_way():
    gateway = Gateway()

    async def wait():
        lab = AsyncClient("http://gateway")
        lab.http = httpx.AsyncClient(base_url="http://gateway", transport=httpx.MockTransport(gateway))
        try:
            await lab.wait(RUN, timeout=0.05, poll_s=0.01, stop_on_timeout=True)
        finally:
            await lab.http.aclose()

    with pytest.raises(WaitTimeout, match="it was stopped"):
        asyncio.run(wait())
    assert len(gateway.stops) == 1


def test_a_run_nobody_started_is_said_at_once_not_waited_out():
    """A typo in a run id waited out the whole timeout (300 s in the README's example):
    a 404 is asked again only for the run the status names (started, not recorded yet)."""
    gateway = Gateway(servoing=RUN)
    lab = client_on(gateway)
    with pytest.raises(client_module.SemservoError, match="404"):
        lab.wait("20261127-000000-000000", timeout=30, poll_s=0.01)
    unrecorded = Gateway(servoing="20261127-000000-000000")
    lab = client_on(unrecorded)
    with pytest.raises(WaitTimeout):  # the status names it: not recorded yet, asked again until the deadline
        lab.wait("20261127-000000-000000", timeout=0.05, poll_s=0.01)

    async def wait_async():
        other = AsyncClient("http://gateway")
        other.http = httpx.AsyncClient(base_url="http://gateway", transport=httpx.MockTransport(Gateway()))
        try:
            await other.wait("20261127-000000-000000", timeout=30, poll_s=0.01)
        finally:
            await other.http.aclose()

    with pytest.raises(client_module.SemservoError, match="404"):
        asyncio.run(wait_async())


def test_a_finished_run_is_returned_whatever_the_timeout():
    gateway = Gateway(finished_after=0)
    assert client_on(gateway).wait(RUN, timeout=-1).state == "converged" and gateway.polls == 1


def test_a_number_json_cannot_carry_is_a_semservo_error_and_nothing_is_sent():
    """NaN or infinity in a body raised httpx's bare ValueError ('Out of range float
    values are not JSON compliant'); the README promises SemservoError for every failure."""
    gateway = Gateway()
    lab = client_on(gateway)
    with pytest.raises(client_module.SemservoError, match="not a finite number .* in tolerance_px") as raised:
        lab.start(tolerance_px=float("nan"))
    assert raised.value.status == 422 and raised.value.field == "tolerance_px"
    with pytest.raises(client_module.SemservoError, match="x_um"):
        lab.move(x_um=float("inf"))
    assert gateway.polls == 0 and not gateway.stops
