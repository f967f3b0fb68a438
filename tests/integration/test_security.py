"""CURVE on every ZeroMQ socket (two-PC deployments): keys made by `semservo keys`, a
service refusing to leave loopback without them, and with them nothing readable or
answerable to a peer without an authorized key."""

from __future__ import annotations

import subprocess
import sys

import pytest
import zmq
import zmq.auth

from semservo import security
from semservo.config import connect
from semservo.transport import ControlClient, FrameSubscriber, ServiceUnavailable
from tests.integration.helpers import start_service, stop, wait_healthy

pytestmark = pytest.mark.integration


def test_keys_are_made_once_and_kept(tmp_path):
    result = subprocess.run([sys.executable, "-m", "semservo", "keys", str(tmp_path / "keys")],
                            capture_output=True, text=True, check=True)
    assert "SEMSERVO_CURVE_KEYS_DIR" in result.stdout
    secret = (tmp_path / "keys" / "server.key_secret").read_bytes()
    assert oct((tmp_path / "keys" / "server.key_secret").stat().st_mode)[-3:] == "600"
    security.make_keys(tmp_path / "keys")  # again: the deployed keys stay
    assert (tmp_path / "keys" / "server.key_secret").read_bytes() == secret
    assert (tmp_path / "keys" / "authorized" / "client.key").is_file()


def test_a_service_off_loopback_without_keys_refuses_to_start(monkeypatch, ports):
    monkeypatch.setenv("SEMSERVO_BIND_HOST", "0.0.0.0")
    monkeypatch.delenv("SEMSERVO_CURVE_KEYS_DIR", raising=False)
    result = subprocess.run([sys.executable, "-m", "semservo", "service", "estimator"], capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 2
    assert "refusing to start" in result.stderr and "semservo keys" in result.stderr
    assert "Traceback" not in result.stderr


def test_with_keys_only_authorized_curve_peers_get_frames_and_answers(tmp_path, monkeypatch, ports, recorded_run):
    keys = tmp_path / "keys"
    security.make_keys(keys)
    monkeypatch.setenv("SEMSERVO_CURVE_KEYS_DIR", str(keys))
    server = start_service("imageserver", "--replay-dir", str(recorded_run), "--fps", "50")
    secure = security.context(keys)
    plain = zmq.Context()
    stranger_dir = tmp_path / "stranger"
    stranger_dir.mkdir()
    zmq.auth.create_certificates(stranger_dir, "client")  # a client keypair nobody authorized
    for name in ("server.key",):
        (stranger_dir / name).write_bytes((keys / name).read_bytes())
    stranger = security.context(stranger_dir)
    control = connect("127.0.0.1", ports["control"])
    try:
        # The launcher's and the tests' own clients take the secured default context.
        wait_healthy(control, server)
        frames = FrameSubscriber(connect("127.0.0.1", ports["frames"]), max_message_bytes=2**26, context=secure)
        assert frames.receive(timeout_s=10) is not None, "an authorized CURVE peer gets frames"
        frames.close()

        for outsider in (plain, stranger):
            client = ControlClient(control, timeout_s=0.5, retries=1, context=outsider)
            with pytest.raises(ServiceUnavailable):
                client.request("health")
            client.close()
            eavesdropper = FrameSubscriber(connect("127.0.0.1", ports["frames"]), max_message_bytes=2**26,
                                           context=outsider)
            assert eavesdropper.receive(timeout_s=1.5) is None, "no frame for a peer without an authorized key"
            eavesdropper.close()
    finally:
        code, output = stop(server)
        for each in (secure, plain, stranger):
            each.destroy(linger=0)
    assert code == 0, output


def test_ws_events_need_the_token_when_one_is_set():
    """The WebSocket is checked like every other endpoint (in-process app, no services)."""
    from fastapi.testclient import TestClient
    from starlette.websockets import WebSocketDisconnect

    from services.gateway.app import create_app
    from services.gateway.core import GatewayCore
    from services.gateway.records import RunStore

    app = create_app(GatewayCore({}, RunStore(":memory:")), api_token="s3cret")
    with TestClient(app) as http:
        with pytest.raises(WebSocketDisconnect) as refused, http.websocket_connect("/events") as socket:
            socket.receive_json()
        assert refused.value.code == 1008
        with http.websocket_connect("/events?token=s3cret") as socket:
            assert socket.receive_json()["kind"] == "hello"
        with http.websocket_connect("/events", headers={"Authorization": "Bearer s3cret"}) as socket:
            assert socket.receive_json()["kind"] == "hello"


def test_the_whole_system_runs_on_curve(tmp_path, monkeypatch, ports):
    """`semservo up --check` with keys: every service binds and connects with CURVE, the
    launcher's health checks and the check's frame and motion streams included."""
    security.make_keys(tmp_path / "keys")
    monkeypatch.setenv("SEMSERVO_CURVE_KEYS_DIR", str(tmp_path / "keys"))
    monkeypatch.setenv("SEMSERVO_CONTROLLER__RUNS_DIR", str(tmp_path / "runs"))
    monkeypatch.setenv("SEMSERVO_GATEWAY__DATABASE", str(tmp_path / "runs" / "semservo.sqlite"))
    result = subprocess.run([sys.executable, "-m", "semservo", "up", "--check", "--frames", "3"],
                            capture_output=True, text=True, timeout=180)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-2000:]
    for name in ("fakelab", "imageserver", "estimator", "stage", "controller", "gateway"):
        assert f"{name} healthy" in result.stdout
    assert "check passed" in result.stdout
