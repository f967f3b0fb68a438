"""ZeroMQ patterns, as the zguide describes them, in one place.

* :class:`FramePublisher` / :class:`FrameSubscriber`: PUB/SUB frames, multipart and
  zero-copy. ``ZMQ_CONFLATE`` cannot give "latest frame only" here because it keeps one
  *part* of a multipart message. A latest-only subscriber instead drains its queue on
  every read, keeping the newest valid frame and counting the stale ones it skipped.
  Its queue is short but not minimal: when a PUB/SUB queue is full it is the *newest*
  message that is dropped, so a queue of 1 or 2 would hand out old frames after any
  hiccup; 8 frames absorb a stalled consumer and draining keeps it current.
* :class:`ControlClient`: request-reply with a timeout and retries (the lazy-pirate
  pattern): a REQ socket that gets no answer in time is closed, reopened and tried
  again, and after the last try :class:`ServiceUnavailable` is raised. Nothing blocks
  forever.
* :class:`ControlServer`: the REP side; it checks every request and always replies.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from typing import Any, Callable

import numpy as np
import pydantic
import zmq

from semservo.errors import BadRequest, CommandError, RequestCancelled, ServiceUnavailable, describe_validation_error
from semservo.messages import FRAME_TOPIC, Reply, Request
from semservo.security import default_context
from semservo.wire import Frame, WireError, decode_frame, encode_frame, frame_header

log = logging.getLogger(__name__)

#: The transport-level cap: ZeroMQ disconnects a peer that sends a part larger than
#: this multiple of the application limit, so nothing huge is ever allocated. Messages
#: between the two limits are received, dropped and counted as ``oversized``.
TRANSPORT_CAP_FACTOR = 4


#: TCP keepalive on every subscriber's connection: a connection silent this long (idle,
#: then unanswered probes) is dropped and dialled again, the publisher's name resolved
#: again. Without it a connection across a cut network (a LAN cable pulled between the
#: two PCs, a container's network disconnected) stays "established" for ever: a
#: subscriber, which never sends, would wait for frames that can no longer come after the
#: network is back. Not ZMTP heartbeats: libzmq 4.3 aborts (``Assertion failed:
#: _input_stopped``, zeromq/libzmq#3937) when a heartbeat times out on a subscriber whose
#: queue is full, and a busy subscriber's queue is full by design (latest frame only).
KEEPALIVE_IDLE_S = 2
KEEPALIVE_INTERVAL_S = 1
KEEPALIVE_PROBES = 3


def _keep_alive(socket: zmq.Socket) -> None:
    socket.setsockopt(zmq.TCP_KEEPALIVE, 1)
    socket.setsockopt(zmq.TCP_KEEPALIVE_IDLE, KEEPALIVE_IDLE_S)
    socket.setsockopt(zmq.TCP_KEEPALIVE_INTVL, KEEPALIVE_INTERVAL_S)
    socket.setsockopt(zmq.TCP_KEEPALIVE_CNT, KEEPALIVE_PROBES)


def _limit_socket(socket: zmq.Socket, max_message_bytes: int) -> None:
    socket.setsockopt(zmq.MAXMSGSIZE, TRANSPORT_CAP_FACTOR * max_message_bytes)
    socket.setsockopt(zmq.LINGER, 0)
    _keep_alive(socket)


class FramePublisher:
    """PUB socket that sends frames. Slow subscribers lose frames, never stall us."""

    def __init__(self, endpoint: str, *, context: zmq.Context | None = None, send_hwm: int = 8):
        self.context = context or default_context()
        self.socket = self.context.socket(zmq.PUB)
        self.socket.setsockopt(zmq.SNDHWM, send_hwm)
        self.socket.setsockopt(zmq.LINGER, 0)
        self.socket.bind(endpoint)
        self.endpoint = self.socket.getsockopt_string(zmq.LAST_ENDPOINT)
        self.sent = 0

    def publish(self, pixels: np.ndarray, *, seq: int, acquired_at_ns: int, **metadata) -> None:
        """Send one frame; ``metadata`` fills the rest of :class:`FrameHeader`."""
        header = frame_header(pixels, seq=seq, acquired_at_ns=acquired_at_ns, **metadata)
        self.socket.send_multipart(encode_frame(header, pixels), copy=False)
        self.sent += 1

    def close(self) -> None:
        self.socket.close(linger=0)


class FrameSubscriber:
    """SUB socket that receives and checks frames.

    ``latest_only=True`` (the default) is for consumers that work on the newest frame:
    every :meth:`receive` drains what queued up and returns the newest valid frame.
    ``latest_only=False`` returns every frame in order (for recorders and benchmarks).
    ``counters`` gets ``frames_received``, ``frames_stale`` and ``dropped_<reason>``.
    """

    def __init__(
        self,
        endpoint: str,
        *,
        max_message_bytes: int,
        latest_only: bool = True,
        context: zmq.Context | None = None,
        counters: Counter | None = None,
        receive_hwm: int | None = None,
    ):
        self.context = context or default_context()
        self.max_message_bytes = max_message_bytes
        self.latest_only = latest_only
        self.counters = counters if counters is not None else Counter()
        self.last_error: str | None = None
        self.socket = self.context.socket(zmq.SUB)
        self.socket.setsockopt(zmq.RCVHWM, receive_hwm or (8 if latest_only else 1000))
        _limit_socket(self.socket, max_message_bytes)
        self.socket.setsockopt(zmq.SUBSCRIBE, FRAME_TOPIC)
        self.socket.connect(endpoint)

    def _decode(self, parts) -> Frame | None:
        try:
            frame = decode_frame(parts, max_bytes=self.max_message_bytes)
        except WireError as error:
            self.counters[f"dropped_{error.reason}"] += 1
            self.last_error = str(error)
            log.warning("dropped a message: %s", error)
            return None
        except Exception as error:  # a message no check foresaw must not stop the receiver
            self.counters["dropped_invalid"] += 1
            self.last_error = f"invalid: {type(error).__name__}: {error}"
            log.exception("dropped a message no check foresaw")
            return None
        self.counters["frames_received"] += 1
        return frame

    def receive(self, timeout_s: float | None = None) -> Frame | None:
        """The next frame (newest if ``latest_only``), or None after ``timeout_s``.

        ``timeout_s=None`` waits until a frame arrives.
        """
        timeout_ms = None if timeout_s is None else max(0, int(timeout_s * 1000))
        if not self.socket.poll(timeout_ms):
            return None
        if not self.latest_only:
            return self._decode(self.socket.recv_multipart(copy=False))
        newest = None
        while True:
            try:
                parts = self.socket.recv_multipart(zmq.NOBLOCK, copy=False)
            except zmq.Again:
                return newest
            frame = self._decode(parts)
            if frame is not None:
                if newest is not None:
                    self.counters["frames_stale"] += 1
                newest = frame

    def close(self) -> None:
        self.socket.close(linger=0)


class MessagePublisher:
    """PUB socket for small typed JSON messages on one topic: ``[topic, json]``."""

    def __init__(self, endpoint: str, topic: bytes, *, context: zmq.Context | None = None):
        self.context = context or default_context()
        self.topic = topic
        self.socket = self.context.socket(zmq.PUB)
        self.socket.setsockopt(zmq.LINGER, 0)
        self.socket.bind(endpoint)
        self.endpoint = self.socket.getsockopt_string(zmq.LAST_ENDPOINT)
        self.sent = 0

    def publish(self, message: pydantic.BaseModel) -> None:
        self.socket.send_multipart([self.topic, message.model_dump_json().encode()])
        self.sent += 1

    def close(self) -> None:
        self.socket.close(linger=0)


class MessageSubscriber:
    """SUB socket for typed JSON messages on one topic; invalid ones are dropped and
    counted (``dropped_parts``, ``dropped_oversized``, ``dropped_message``)."""

    def __init__(self, endpoint: str, topic: bytes, model: type[pydantic.BaseModel], *,
                 max_message_bytes: int = 2**20, context: zmq.Context | None = None,
                 counters: Counter | None = None):
        self.context = context or default_context()
        self.topic = topic
        self.model = model
        self.max_message_bytes = max_message_bytes
        self.counters = counters if counters is not None else Counter()
        self.last_error: str | None = None
        self.socket = self.context.socket(zmq.SUB)
        _limit_socket(self.socket, max_message_bytes)
        self.socket.setsockopt(zmq.SUBSCRIBE, topic)
        self.socket.connect(endpoint)

    def _drop(self, reason: str, detail: str) -> None:
        self.counters[f"dropped_{reason}"] += 1
        self.last_error = f"{reason}: {detail}"
        log.warning("dropped a %s message: %s", self.topic.decode(), detail)

    def receive(self, timeout_s: float | None = None):
        """The next valid message, or None after ``timeout_s``."""
        deadline_ms = None if timeout_s is None else max(0, int(timeout_s * 1000))
        while self.socket.poll(deadline_ms):
            parts = self.socket.recv_multipart()
            if len(parts) != 2 or parts[0] != self.topic:
                self._drop("parts", f"expected [{self.topic!r}, json], got {len(parts)} parts")
            elif len(parts[1]) > self.max_message_bytes:
                self._drop("oversized", f"{len(parts[1])} bytes")
            else:
                try:
                    message = self.model.model_validate_json(parts[1])
                except pydantic.ValidationError as error:
                    self._drop("message", str(error.errors()[0]["msg"]))
                else:
                    self.counters["messages_received"] += 1
                    return message
            deadline_ms = 0 if deadline_ms is not None else None
        return None

    def close(self) -> None:
        self.socket.close(linger=0)


class ControlClient:
    """Lazy-pirate request-reply client for one service's control socket."""

    def __init__(
        self,
        endpoint: str,
        *,
        timeout_s: float = 1.0,
        retries: int = 3,
        context: zmq.Context | None = None,
        max_message_bytes: int = 16 * 2**20,
    ):
        self.endpoint = endpoint
        self.timeout_s = timeout_s
        self.retries = retries
        self.max_message_bytes = max_message_bytes
        self.context = context or default_context()
        self.socket: zmq.Socket | None = None
        #: Asked while waiting for any reply: True abandons it (e.g. the process is stopping).
        self.cancelled: Callable[[], bool] | None = None
        #: No reply is waited for longer than this, whatever its command declares (a
        #: stopping service bounds every last call: a command's own 5 s would outlast
        #: the launcher's patience with a dead peer). None: no bound.
        self.max_timeout_s: float | None = None

    def _open(self) -> zmq.Socket:
        socket = self.context.socket(zmq.REQ)
        _limit_socket(socket, self.max_message_bytes)
        socket.connect(self.endpoint)
        return socket

    def _discard(self) -> None:
        # A REQ socket that sent and got no reply is stuck in its state machine: the
        # lazy pirate closes it and opens a fresh one.
        if self.socket is not None:
            self.socket.close(linger=0)
            self.socket = None

    def request_parts(self, payload: bytes, *, timeout_s: float | None = None, retries: int | None = None,
                      cancelled: Callable[[], bool] | None = None) -> list:
        """Send raw bytes; return every part of the reply (zero-copy zmq frames).

        ``cancelled`` is asked every 100 ms while waiting; when it says so the request
        is abandoned (the socket replaced) and :class:`RequestCancelled` raised.
        """
        timeout_s = timeout_s or self.timeout_s
        if self.max_timeout_s is not None:
            timeout_s = min(timeout_s, self.max_timeout_s)
        cancelled = cancelled or self.cancelled
        for attempt in range(1, (retries or self.retries) + 1):
            if self.socket is None:
                self.socket = self._open()
            self.socket.send(payload)
            deadline = time.monotonic() + timeout_s
            while (remaining := deadline - time.monotonic()) > 0:
                if self.socket.poll(int(1000 * min(remaining, 0.1)), zmq.POLLIN):
                    return self.socket.recv_multipart(copy=False)
                if cancelled is not None and cancelled():
                    self._discard()
                    raise RequestCancelled(f"request to {self.endpoint} cancelled")
            log.debug("no reply from %s (try %d)", self.endpoint, attempt)
            self._discard()
        raise ServiceUnavailable(f"no reply from {self.endpoint} after {retries or self.retries} tries")

    def request_raw(self, payload: bytes, *, timeout_s: float | None = None, retries: int | None = None) -> bytes:
        """Send raw bytes and return the raw (one-part) reply (for tests of malformed input)."""
        return self.request_parts(payload, timeout_s=timeout_s, retries=retries)[0].bytes

    def request(self, command: str, *, timeout_s: float | None = None, retries: int | None = None, **args: Any) -> dict:
        """Send a command; return its result or raise CommandError / ServiceUnavailable."""
        payload = Request(command=command, args=args).model_dump_json().encode()
        raw = self.request_raw(payload, timeout_s=timeout_s, retries=retries)
        reply = Reply.model_validate_json(raw)
        if not reply.ok:
            raise CommandError(reply.error.code, reply.error.message, **(reply.error.details or {}))
        return reply.result or {}

    def close(self) -> None:
        self._discard()


Handler = Callable[[dict[str, Any]], dict[str, Any] | None]

__all__ = ["BadRequest", "CommandError", "ControlClient", "ControlServer", "FramePublisher", "FrameSubscriber",
           "MessagePublisher", "MessageSubscriber", "RequestCancelled", "ServiceUnavailable", "number"]


def number(value: Any, name: str, unit: str = "") -> float:
    """A command argument that must be a finite JSON number (``true`` is not 1, NaN and
    infinities are refused): the value as float, else :class:`BadRequest` naming it."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise BadRequest(f"{name} must be a finite number{' of ' + unit if unit else ''}, got {value!r}")
    return float(value)


class ControlServer:
    """REP socket that dispatches commands to handlers and always replies.

    A malformed request (not JSON, wrong version, unknown command, too large, more than
    one part) gets an error reply and is counted; the service goes on.
    """

    def __init__(
        self,
        endpoint: str,
        *,
        max_message_bytes: int,
        context: zmq.Context | None = None,
        counters: Counter | None = None,
    ):
        self.context = context or default_context()
        self.max_message_bytes = max_message_bytes
        self.counters = counters if counters is not None else Counter()
        self.handlers: dict[str, Handler] = {}
        self.last_error: str | None = None
        self.socket = self.context.socket(zmq.REP)
        _limit_socket(self.socket, max_message_bytes)
        self.socket.bind(endpoint)
        self.endpoint = self.socket.getsockopt_string(zmq.LAST_ENDPOINT)

    def register(self, command: str, handler: Handler) -> None:
        self.handlers[command] = handler

    def _reject(self, code: str, message: str, details: dict[str, Any] | None = None,
                transient: bool = False) -> Reply:
        self.counters[f"rejected_{code}"] += 1
        # A caller polling ("not enough frames yet") is not a problem to warn about nor
        # to show in health: a teach of 4 frames on a slow source logged fifteen
        # warnings while it waited.
        if not transient:
            self.last_error = f"{code}: {message}"
        log.log(logging.DEBUG if transient else logging.WARNING, "rejected a request: %s: %s", code, message)
        return Reply.failure(code, message, details)

    def _answer(self, parts: list[bytes]) -> Reply:
        if len(parts) != 1:
            return self._reject("bad_request", f"expected one JSON part, got {len(parts)}")
        if len(parts[0]) > self.max_message_bytes:
            return self._reject("oversized", f"{len(parts[0])} bytes exceeds {self.max_message_bytes}")
        try:
            request = Request.model_validate_json(parts[0])
        except pydantic.ValidationError as error:
            first = error.errors()[0]
            if first["loc"] == ("v",):
                return self._reject("version", f"unsupported wire version: {first['msg']}")
            return self._reject("bad_request", describe_validation_error(error))
        handler = self.handlers.get(request.command)
        if handler is None:
            known = ", ".join(sorted(self.handlers))
            return self._reject("unknown_command", f"{request.command!r} is not one of: {known}")
        self.counters[f"command_{request.command}"] += 1
        try:
            return Reply.success(handler(request.args))
        except CommandError as error:  # a refusal with its code (bad_request, or a rule such as a stage limit)
            return self._reject(error.code, error.message, error.extra, transient=error.transient)
        except Exception as error:  # a handler bug must not take the service down
            log.exception("command %s failed", request.command)
            return self._reject("internal", f"{type(error).__name__}: {error}")

    def handle_one(self) -> None:
        """Receive one request (it must be waiting) and send its reply."""
        parts = self.socket.recv_multipart()
        self.socket.send(self._answer(parts).model_dump_json().encode())

    def close(self) -> None:
        self.socket.close(linger=0)
