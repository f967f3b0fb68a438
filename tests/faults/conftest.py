"""One real stack for the fault tests, as ``semservo up --restart`` runs it: every
service a process, the launcher restarting what dies, the lab at 20x speed."""

from __future__ import annotations

import pytest

from semservo.client import Client
from semservo.config import Settings
from semservo.faults import Campaign
from semservo.launcher import Launcher
from tests.conftest import choose_ports, run_lab_faster

SPEEDUP = 20


@pytest.fixture(scope="package")
def stack(tmp_path_factory):
    folder = tmp_path_factory.mktemp("faults")
    with pytest.MonkeyPatch.context() as env:
        choose_ports(env)
        run_lab_faster(env, SPEEDUP, fps=30)
        env.setenv("SEMSERVO_CONTROLLER__RUNS_DIR", str(folder / "runs"))
        env.setenv("SEMSERVO_GATEWAY__DATABASE", str(folder / "runs" / "semservo.sqlite"))
        settings = Settings()
        log = (folder / "services.log").open("w")
        launcher = Launcher(settings, restart=True, max_restarts=20, out=log)
        launcher.start(timeout_s=90)
        client = Client(f"http://127.0.0.1:{settings.gateway.http_port}", timeout=15)
        try:
            with Campaign(launcher, client, settings, say=lambda text: log.write(text + "\n")) as campaign:
                yield campaign
        finally:
            client.close()
            launcher.stop()
            log.close()


@pytest.fixture
def campaign(stack) -> Campaign:
    """The stack, healthy (a test that broke it leaves it restarted and reconnected)."""
    stack.all_healthy()
    return stack
