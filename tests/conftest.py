"""Shared fixtures: the real recording, free loopback ports, an isolated settings env."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
import zmq

from semservo.config import find_recorded_run, find_sem_images
from semservo.launcher import PORT_SETTINGS, faster_lab_environment, free_port, fresh_port_environment, simulated_system

__all__ = ["PORT_SETTINGS", "choose_ports", "free_port", "run_lab_faster", "serve_until", "simulated_stack"]


@pytest.fixture(scope="session")
def recorded_run() -> Path:
    """The real 2013 SEM run, found through the setting's default (never copied here)."""
    folder = find_recorded_run()
    assert (folder / "reference.png").is_file(), (
        f"the recorded SEM run is missing at {folder}; it lives in shared/data beside the checkout"
    )
    return folder


@pytest.fixture(scope="session")
def sem_images() -> Path:
    """The real SEM images of other instruments, found through the setting's default."""
    folder = find_sem_images()
    assert (folder / "README.md").is_file(), (
        f"the real SEM images are missing at {folder}; they live in shared/data beside the checkout"
    )
    return folder


def choose_ports(env: pytest.MonkeyPatch) -> dict[str, int]:
    """Fresh loopback ports for every service, set in the environment children inherit
    (:func:`semservo.launcher.fresh_port_environment`). Returns them by short name."""
    variables = fresh_port_environment()
    for name, value in variables.items():
        env.setenv(name, value)
    return {name: int(variables[variable]) for name, variable in PORT_SETTINGS.items()}


def run_lab_faster(env: pytest.MonkeyPatch, speedup: float, fps: float = 100.0) -> None:
    """The simulated lab's clock ``speedup`` times faster (see
    :func:`semservo.launcher.faster_lab_environment`)."""
    for name, value in faster_lab_environment(speedup, fps).items():
        env.setenv(name, value)


@pytest.fixture
def ports(monkeypatch) -> dict[str, int]:
    return choose_ports(monkeypatch)


@pytest.fixture
def context():
    ctx = zmq.Context()
    yield ctx
    ctx.destroy(linger=0)  # closes sockets a failed test left open, then terminates


#: The whole system on simulated hardware, on fresh ports (the library's helper).
simulated_stack = simulated_system


def serve_until(server, stop: threading.Event) -> int:
    """Answer every request to a :class:`~semservo.transport.ControlServer`, as a service
    does, until ``stop``; returns how many."""
    handled = 0
    while not stop.is_set():
        if server.socket.poll(50):
            server.handle_one()
            handled += 1
    return handled
