"""Shared fixtures: the real recording, free loopback ports, an isolated settings env."""

from __future__ import annotations

import random
import socket
import tempfile
from contextlib import contextmanager
from pathlib import Path

import pytest
import zmq

from semservo.config import find_recorded_run, find_sem_images


def _ephemeral_range() -> tuple[int, int]:
    try:
        low, high = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(low), int(high)
    except (OSError, ValueError):
        return 32768, 60999  # Linux's default


#: Ports already handed out in this session, never handed out twice (a service of an
#: earlier test may still be letting go of its port).
_handed_out: set[int] = set()
_port_picker = random.Random()


def free_port() -> int:
    """A loopback port free now, chosen *below* the kernel's ephemeral range.

    A port the kernel picked for us (bind to 0) lies inside the ephemeral range, so in
    the moment between choosing it and the service binding it, any outgoing connection
    (every ZeroMQ connect, every HTTP client) may be given it as its local port: CI once
    lost a test to exactly that. Ports below the range are never given out that way.
    """
    ephemeral_low, _ = _ephemeral_range()
    low, high = 15000, max(15000 + 2000, ephemeral_low - 1)
    for _ in range(500):
        port = _port_picker.randint(low, high)
        if port in _handed_out:
            continue
        with socket.socket() as probe:
            try:
                probe.bind(("127.0.0.1", port))
            except OSError:
                continue
        _handed_out.add(port)
        return port
    raise RuntimeError(f"no free loopback port in {low}..{high}")


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


#: Every port a service binds, by the name tests use, and the setting that holds it.
PORT_SETTINGS = {
    "frames": "SEMSERVO_IMAGESERVER__FRAMES_PORT", "control": "SEMSERVO_IMAGESERVER__CONTROL_PORT",
    "motion": "SEMSERVO_ESTIMATOR__MOTION_PORT", "estimator_control": "SEMSERVO_ESTIMATOR__CONTROL_PORT",
    "fakelab_control": "SEMSERVO_FAKELAB__CONTROL_PORT", "scan": "SEMSERVO_FAKELAB__SCAN_PORT",
    "serial_tcp": "SEMSERVO_FAKELAB__SERIAL_TCP_PORT", "stage_control": "SEMSERVO_STAGE__CONTROL_PORT",
    "controller_control": "SEMSERVO_CONTROLLER__CONTROL_PORT", "controller_status": "SEMSERVO_CONTROLLER__STATUS_PORT",
    "gateway_http": "SEMSERVO_GATEWAY__HTTP_PORT", "gateway_control": "SEMSERVO_GATEWAY__CONTROL_PORT",
}


def choose_ports(env: pytest.MonkeyPatch) -> dict[str, int]:
    """Fresh loopback ports for every service, set in the environment children inherit
    (the stage service finds the emulated NV 40/3 on the chosen TCP port), and a fresh
    folder for what the stage service keeps across restarts (no test inherits another's
    armed or stopped stage)."""
    chosen = {name: free_port() for name in PORT_SETTINGS}
    for name, variable in PORT_SETTINGS.items():
        env.setenv(variable, str(chosen[name]))
    env.setenv("SEMSERVO_STAGE__SERIAL_URL", f"socket://127.0.0.1:{chosen['serial_tcp']}")
    env.setenv("SEMSERVO_STAGE__STATE_DIR", tempfile.mkdtemp(prefix="semservo-stage-"))
    return chosen


def run_lab_faster(env: pytest.MonkeyPatch, speedup: float, fps: float = 100.0) -> None:
    """The simulated lab's clock ``speedup`` times faster, the stage's rate limit scaled
    with it (as ``semservo up --speedup`` does), the image server as fast as ``fps``."""
    env.setenv("SEMSERVO_FAKELAB__SPEEDUP", str(speedup))
    env.setenv("SEMSERVO_STAGE__MAX_RATE_V_PER_S", str(200 * speedup))
    env.setenv("SEMSERVO_IMAGESERVER__FPS", str(fps))


@pytest.fixture
def ports(monkeypatch) -> dict[str, int]:
    return choose_ports(monkeypatch)


@pytest.fixture
def context():
    ctx = zmq.Context()
    yield ctx
    ctx.destroy(linger=0)  # closes sockets a failed test left open, then terminates


@contextmanager
def simulated_stack(folder: Path, *, speedup: float = 20, fps: float = 100, restart: bool = False, out=None,
                    **settings: str):
    """The whole system on simulated hardware (the launcher, fresh loopback ports, the lab
    ``speedup`` x faster), its records in ``folder``; ``settings`` are more SEMSERVO_*
    variables. Yields (launcher, settings); everything is stopped afterwards."""
    from semservo.config import Settings
    from semservo.launcher import Launcher

    with pytest.MonkeyPatch.context() as env:
        choose_ports(env)
        run_lab_faster(env, speedup, fps)
        env.setenv("SEMSERVO_CONTROLLER__RUNS_DIR", str(folder / "runs"))
        env.setenv("SEMSERVO_GATEWAY__DATABASE", str(folder / "runs" / "semservo.sqlite"))
        for name, value in settings.items():
            env.setenv(name, value)
        resolved = Settings()
        log = out or (folder / "services.log").open("w")
        launcher = Launcher(resolved, restart=restart, max_restarts=20, out=log)
        launcher.start(timeout_s=90)
        try:
            yield launcher, resolved
        finally:
            launcher.stop()
            if out is None:
                log.close()
