"""One real stack for the fault tests, as ``semservo up --restart`` runs it: every
service a process, the launcher restarting what dies, the lab at 20x speed."""

from __future__ import annotations

import pytest

from semservo.client import Client
from semservo.faults import Campaign
from tests.conftest import simulated_stack

SPEEDUP = 20


@pytest.fixture(scope="package")
def stack(tmp_path_factory):
    folder = tmp_path_factory.mktemp("faults")
    with (folder / "services.log").open("w") as log, \
            simulated_stack(folder, speedup=SPEEDUP, fps=30, restart=True, out=log) as (launcher, settings):
        with Client(f"http://127.0.0.1:{settings.gateway.http_port}", timeout=15) as client, \
                Campaign(launcher, client, settings, say=lambda text: log.write(text + "\n")) as campaign:
            yield campaign


@pytest.fixture
def campaign(stack) -> Campaign:
    """The stack, healthy (a test that broke it leaves it restarted and reconnected)."""
    stack.all_healthy()
    return stack
