"""Gateway process: the REST API (FastAPI on uvicorn, in a thread) in front of the
ZeroMQ services, plus a health socket for the launcher.

Sockets: SUB to the image server's frames (latest only, for the images it serves), SUB
to the controller's status stream (recorded into SQLite, relayed on ``WS /events``),
REQ to every service's control socket (one lock each: HTTP requests arrive on many
threads, a ZeroMQ socket serves one).

Bound to loopback by default; on any other address it refuses to start without
``SEMSERVO_GATEWAY__API_TOKEN``. Run it with ``semservo service gateway``.
"""

from __future__ import annotations

import argparse
import logging
import threading
import time
from pathlib import Path

import uvicorn

from semservo.config import Settings, connect
from semservo.logs import configure
from semservo.messages import CONTROLLER_TOPIC, ControllerEvent
from semservo.protocol import ServicePort
from semservo.security import is_loopback
from semservo.service import ServiceRuntime
from semservo.transport import ControlClient, FrameSubscriber, MessageSubscriber
from services.gateway.app import create_app
from services.gateway.core import GatewayCore
from services.gateway.records import RunStore

log = logging.getLogger("gateway")

#: The dashboard's files (vendored: no CDN), served at ``/``.
DASHBOARD = Path(__file__).parent / "dashboard"


def build_parser() -> argparse.ArgumentParser:
    return argparse.ArgumentParser(
        prog="semservo service gateway",
        description="The REST API, its OpenAPI docs (/docs) and the dashboard, in front of the services. "
                    "Settings SEMSERVO_GATEWAY__* (HTTP_HOST, HTTP_PORT, API_TOKEN, DATABASE).",
    )


def main(argv: list[str] | None = None) -> int:
    build_parser().parse_args(argv)
    settings = Settings()
    configure(settings.log_level)
    config = settings.gateway
    token = config.api_token.get_secret_value() if config.api_token else None
    if not is_loopback(config.http_host) and not token:
        log.error("refusing to serve on %s without an API token: set SEMSERVO_GATEWAY__API_TOKEN (or bind to "
                  "127.0.0.1)", config.http_host)
        return 2
    runtime = ServiceRuntime("gateway", settings, settings.bind(config.control_port))
    timeout = min(settings.request_timeout_s, 1.0)

    def port(host: str, control_port: int) -> ServicePort:
        # Shared: HTTP requests arrive on many threads, a ZeroMQ socket serves one at a time.
        return ServicePort(ControlClient(connect(host, control_port), timeout_s=timeout, retries=1,
                                         context=runtime.context), shared=True)

    ports = {
        "fakelab": port(settings.fakelab.host, settings.fakelab.control_port),
        "imageserver": port(settings.imageserver.host, settings.imageserver.control_port),
        "estimator": port(settings.estimator.host, settings.estimator.control_port),
        "stage": port(settings.stage.host, settings.stage.control_port),
        "controller": port(settings.controller.host, settings.controller.control_port),
    }
    store = RunStore(config.database)
    core = GatewayCore(ports, store, frames_dir=config.database.parent / "frames" if config.save_frames else None,
                       camera=settings.controller.camera_to_stage())
    app = create_app(core, api_token=token, max_upload_bytes=config.max_upload_bytes,
                     static_dir=DASHBOARD if DASHBOARD.is_dir() else None)
    core.broadcast = app.state.publish

    frames = FrameSubscriber(connect(settings.imageserver.host, settings.imageserver.frames_port),
                             max_message_bytes=settings.max_message_bytes, context=runtime.context,
                             counters=runtime.counters)
    events = MessageSubscriber(connect(settings.controller.host, settings.controller.status_port),
                               CONTROLLER_TOPIC, ControllerEvent, context=runtime.context, counters=runtime.counters)

    def on_frame() -> None:
        frame = frames.receive(timeout_s=0)
        if frame is not None:
            core.on_frame(frame)

    def on_event() -> None:
        while (event := events.receive(timeout_s=0)) is not None:
            try:
                core.on_event(event)
            except Exception:  # one bad record must not stop the recording of the rest
                log.exception("could not record controller event %s", event.kind)
                runtime.error(f"could not record a {event.kind} event")

    runtime.add_reader(frames.socket, on_frame)
    runtime.add_reader(events.socket, on_event)
    runtime.report_errors_from(lambda: frames.last_error)

    server = uvicorn.Server(uvicorn.Config(app, host=config.http_host, port=config.http_port, log_level="warning",
                                           access_log=False, lifespan="on", timeout_graceful_shutdown=2))
    http = threading.Thread(target=server.run, name="http", daemon=True)
    http.start()
    # Healthy means serving HTTP: health is answered only from runtime.run() on.
    deadline = time.monotonic() + 15
    while not server.started and http.is_alive() and time.monotonic() < deadline:
        time.sleep(0.02)
    url = f"http://{config.http_host}:{config.http_port}"
    print(f"semservo gateway: {url}/ (dashboard), {url}/docs (API){' - token required' if token else ''}",
          flush=True)
    runtime.details = lambda: {"http": url, "token_required": bool(token), "database": str(config.database),
                               "frames": core.counters["frames"], "iterations_recorded": core.counters["iterations"],
                               "http_running": http.is_alive()}

    http_failed = threading.Event()
    housekeeping = {"due": 0.0}

    def step() -> float:
        if not http.is_alive() and not http_failed.is_set():
            http_failed.set()
            log.error("the HTTP server stopped: is %s taken?", url)
            runtime.request_stop()
        if time.monotonic() >= housekeeping["due"]:
            # Records are completed even when nobody polls /status (core.reconcile).
            housekeeping["due"] = time.monotonic() + 1.0
            try:
                core.status()
            except Exception:  # noqa: BLE001 - the next round tries again; the reason is logged
                log.exception("housekeeping failed")
        return 0.2

    try:
        runtime.run(step)
        return 1 if http_failed.is_set() else 0
    finally:
        app.state.listeners.close_all()  # open dashboards say goodbye, so the server need not wait for them
        server.should_exit = True
        http.join(timeout=5)
        frames.close()
        events.close()
        for each in ports.values():
            each.close()
        store.close()
        runtime.context.destroy(linger=0)  # closes what is still open: term() would wait on it


if __name__ == "__main__":
    raise SystemExit(main())
