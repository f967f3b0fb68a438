"""Starting and stopping real semservo processes from tests."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

from semservo.messages import Health
from semservo.transport import ControlClient, ServiceUnavailable


def start_service(name: str, *args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "semservo", "service", name, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def wait_healthy(endpoint: str, process: subprocess.Popen, timeout_s: float = 20.0) -> Health:
    deadline = time.monotonic() + timeout_s
    client = ControlClient(endpoint, timeout_s=0.3, retries=1)
    try:
        while time.monotonic() < deadline:
            assert process.poll() is None, f"service exited early:\n{process.stdout.read()}"
            try:
                health = Health.model_validate(client.request("health"))
                if health.healthy:
                    return health
            except ServiceUnavailable:
                time.sleep(0.05)
        raise AssertionError(f"no healthy answer from {endpoint} in {timeout_s} s")
    finally:
        client.close()


def stop(process: subprocess.Popen, sig: int = signal.SIGTERM, timeout_s: float = 10.0) -> tuple[int, str]:
    if process.poll() is None:
        process.send_signal(sig)
    try:
        code = process.wait(timeout_s)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
        raise AssertionError("process did not stop in time") from None
    return code, process.stdout.read()


def wait_for(predicate, timeout_s: float, what: str):
    """Poll ``predicate`` every 0.1 s until it returns something true; that value."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}")
