"""Shared fixtures: the real recording, free loopback ports, an isolated settings env."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest
import zmq

from semservo.config import find_recorded_run


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture(scope="session")
def recorded_run() -> Path:
    """The real 2013 SEM run, found through the setting's default (never copied here)."""
    folder = find_recorded_run()
    assert (folder / "reference.png").is_file(), (
        f"the recorded SEM run is missing at {folder}; it lives in shared/data beside the checkout"
    )
    return folder


@pytest.fixture
def ports(monkeypatch) -> dict[str, int]:
    """Fresh loopback ports for every service, set in the environment children inherit."""
    chosen = {name: free_port() for name in ("frames", "control", "motion", "estimator_control",
                                             "fakelab_control", "scan", "serial_tcp", "stage_control",
                                             "controller_control", "controller_status",
                                             "gateway_http", "gateway_control")}
    monkeypatch.setenv("SEMSERVO_IMAGESERVER__FRAMES_PORT", str(chosen["frames"]))
    monkeypatch.setenv("SEMSERVO_IMAGESERVER__CONTROL_PORT", str(chosen["control"]))
    monkeypatch.setenv("SEMSERVO_ESTIMATOR__MOTION_PORT", str(chosen["motion"]))
    monkeypatch.setenv("SEMSERVO_ESTIMATOR__CONTROL_PORT", str(chosen["estimator_control"]))
    monkeypatch.setenv("SEMSERVO_FAKELAB__CONTROL_PORT", str(chosen["fakelab_control"]))
    monkeypatch.setenv("SEMSERVO_FAKELAB__SCAN_PORT", str(chosen["scan"]))
    monkeypatch.setenv("SEMSERVO_FAKELAB__SERIAL_TCP_PORT", str(chosen["serial_tcp"]))
    monkeypatch.setenv("SEMSERVO_STAGE__CONTROL_PORT", str(chosen["stage_control"]))
    monkeypatch.setenv("SEMSERVO_STAGE__SERIAL_URL", f"socket://127.0.0.1:{chosen['serial_tcp']}")
    monkeypatch.setenv("SEMSERVO_CONTROLLER__CONTROL_PORT", str(chosen["controller_control"]))
    monkeypatch.setenv("SEMSERVO_CONTROLLER__STATUS_PORT", str(chosen["controller_status"]))
    monkeypatch.setenv("SEMSERVO_GATEWAY__HTTP_PORT", str(chosen["gateway_http"]))
    monkeypatch.setenv("SEMSERVO_GATEWAY__CONTROL_PORT", str(chosen["gateway_control"]))
    return chosen


@pytest.fixture
def context():
    ctx = zmq.Context()
    yield ctx
    ctx.destroy(linger=0)  # closes sockets a failed test left open, then terminates
