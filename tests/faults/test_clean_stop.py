"""Ctrl-C after a fault: every service stops by itself in time, even the controller of a
run whose stage service is dead (its shutdown used to wait on the dead peer until the
launcher killed it)."""

from __future__ import annotations

import collections
import io

import pytest
from semservo.client import Client

from tests.conftest import simulated_stack
from tests.integration.helpers import wait_for

pytestmark = pytest.mark.integration


def test_the_stack_stops_cleanly_with_a_run_whose_stage_died(tmp_path):
    output = io.StringIO()
    with simulated_stack(tmp_path, fps=30, out=output) as (launcher, settings), \
            Client(f"http://127.0.0.1:{settings.gateway.http_port}", timeout=15) as lab:
        wait_for(lambda: lab.status()["latest_frame_seq"] is not None, 30, "frames")
        lab.teach()
        lab.move(x_um=6.0)
        run = lab.start(hold=True)
        wait_for(lambda: lab.status()["iteration"] >= 2, 60, "the run moving")
        launcher.children["stage"].process.kill()
    log = output.getvalue()
    assert "did not stop" not in log, log[-3000:]
    for name in ("gateway", "controller", "estimator", "imageserver", "fakelab"):
        assert f"{name} stopped (exit code 0)" in log, name
    assert run["run_id"]


def test_the_stack_stops_cleanly_with_dashboards_listening():
    """Ctrl-C with the dashboard open (a WebSocket listening for events) took the gateway
    past its 5 s and got it killed; the listeners are now told to go."""
    import contextlib
    import tempfile
    import threading
    from pathlib import Path

    from websockets.sync.client import connect

    output = io.StringIO()
    closed = []
    with tempfile.TemporaryDirectory() as folder, contextlib.ExitStack() as sockets_open, \
            simulated_stack(Path(folder), fps=30, out=output) as (launcher, settings):
        url = f"ws://127.0.0.1:{settings.gateway.http_port}/events"
        sockets = [sockets_open.enter_context(connect(url)) for _ in range(3)]

        def listen(socket) -> None:
            try:
                collections.deque(socket, maxlen=0)  # every message, until the server closes it
            finally:
                closed.append(socket.close_code)

        threads = [threading.Thread(target=listen, args=(socket,), daemon=True) for socket in sockets]
        for thread in threads:
            thread.start()
    for thread in threads:
        thread.join(timeout=5)
    log = output.getvalue()
    assert "did not stop" not in log, log[-3000:]
    assert "gateway stopped (exit code 0)" in log
    assert closed == [1001, 1001, 1001], "each listener was told the gateway is going away"
