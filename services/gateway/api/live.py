"""What happens now: Prometheus metrics, and status and iterations on a WebSocket."""

from __future__ import annotations

import asyncio
import json
import logging
import time

from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from fastapi.responses import PlainTextResponse, Response

from services.gateway.api.deps import Core, token_matches, websocket_token
from services.gateway.metrics import metrics_text

log = logging.getLogger("gateway.api")

router = APIRouter(tags=["live"])


@router.get("/metrics", response_class=PlainTextResponse, summary="Prometheus text format")
def metrics(core: Core) -> Response:
    body, content_type = metrics_text(core)
    return Response(body, media_type=content_type)


@router.websocket("/events")
async def events(socket: WebSocket) -> None:
    """Status and per-iteration records as they happen (JSON text messages). With a token
    configured, it must come as ``?token=`` or as a bearer header."""
    app = socket.app
    if not token_matches(app.state.api_token, websocket_token(socket)):
        # Accepted, then closed with the reason: a close before the handshake reaches a
        # browser as a bare 1006, and the dashboard could not say why its plots stay empty.
        await socket.accept()
        await socket.close(code=1008, reason="a valid token is required (?token=...)")
        return
    await socket.accept()
    listeners = app.state.listeners
    queue: asyncio.Queue = asyncio.Queue(maxsize=1000)
    listeners.add(queue)
    closing = listeners.closing
    try:
        await socket.send_text(json.dumps({"kind": "hello", "run_id": None, "data": app.state.core.last_status}))
        while not closing.is_set():
            getting = asyncio.ensure_future(queue.get())
            ending = asyncio.ensure_future(closing.wait())
            done, _ = await asyncio.wait({getting, ending}, return_when=asyncio.FIRST_COMPLETED)
            for pending in (getting, ending):
                if pending not in done:
                    pending.cancel()
            if getting in done:
                await socket.send_text(getting.result())
        # The gateway is stopping: say goodbye, so the browser knows and the server need
        # not wait for it (a dashboard left open kept Ctrl-C waiting before).
        await socket.close(code=1001, reason="the gateway is stopping")
    except WebSocketDisconnect:
        log.debug("an events listener went away")
    finally:
        listeners.discard(queue)


class Listeners(set):
    """The WebSocket listeners' queues, fed from any thread; ``closing`` ends them all."""

    def __init__(self):
        super().__init__()
        self.loop: asyncio.AbstractEventLoop | None = None
        self.closing = asyncio.Event()

    def publish(self, message: dict) -> None:
        """From any thread: hand a message to every listener (a slow one drops)."""
        loop = self.loop
        if loop is None:
            return
        text = json.dumps(message, default=str)

        def deliver() -> None:
            for queue in list(self):
                if not queue.full():
                    queue.put_nowait(text)

        loop.call_soon_threadsafe(deliver)

    def close_all(self, wait_s: float = 1.0) -> None:
        """From any thread but the server's: every listener says goodbye (1001, going
        away) and ends (the server is stopping); waits up to ``wait_s`` for them to have
        done so, or the server's own shutdown would close them first, as a restart (1012)."""
        loop = self.loop
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(self.closing.set)
            deadline = time.monotonic() + wait_s
            while len(self) and time.monotonic() < deadline:
                time.sleep(0.01)
