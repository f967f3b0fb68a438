"""Every service's healthcheck (its compose `semservo health NAME`) reports healthy; a
service whose process is stopped (SIGSTOP: alive, answering nothing) is reported
unhealthy, by the check and by the engine's recorded status, and healthy again after."""

from __future__ import annotations

import os
import signal
import time

from tests.containers.conftest import stack_module


def test_every_healthcheck_reports_healthy(system):
    results = system.stack.health()
    assert set(results) == set(stack_module.SERVICES)
    assert all(ok for ok, _ in results.values()), results
    for service, info in system.stack.containers().items():
        assert info["health"] == "healthy", (service, info)


def test_a_stopped_process_is_reported_unhealthy(system):
    service = "controller"
    pid = system.info(service)["pid"]
    os.kill(pid, signal.SIGSTOP)
    try:
        # Docker runs its checks every 10 s and calls a service unhealthy after 3 misses;
        # podman has no timer here, so the check is run as Docker would.
        deadline = time.monotonic() + 90
        while True:
            ok, output = system.stack.check(service)
            assert not ok, output
            if system.info(service)["health"] == "unhealthy":
                break
            assert time.monotonic() < deadline, system.info(service)
            time.sleep(1.0 if system.engine.name == "podman" else 5.0)
        assert system.info(service)["running"]  # alive, not restarted: only unhealthy
        others = {name: ok for name, (ok, _) in system.stack.health().items() if name != service}
        assert all(others.values()), others
    finally:
        os.kill(pid, signal.SIGCONT)
    assert system.stack.wait_healthy(60, services=(service,))
    assert system.info(service)["health"] == "healthy"
