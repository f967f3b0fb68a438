"""What every service process has in common: a control socket that answers ``health``,
counters, a last error, one poll loop, and a clean stop on SIGTERM or SIGINT.

A service's ``main`` builds a :class:`ServiceRuntime`, registers its commands and the
sockets it reads, and calls :meth:`ServiceRuntime.run` with a ``step`` function that
does its periodic work. The service's core logic stays free of sockets.
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import signal
import sys
import threading
import time
from collections import Counter
from typing import Any, Callable, NoReturn

import zmq

from semservo import security
from semservo.config import Settings
from semservo.messages import Health, ServiceState
from semservo.transport import ControlServer

log = logging.getLogger(__name__)

#: A step does periodic work and returns how many seconds may pass before it is due
#: again (None: only when a socket has something).
Step = Callable[[], float | None]


class ServiceRuntime:
    def __init__(self, name: str, settings: Settings, control_endpoint: str, *, context: zmq.Context | None = None):
        self.name = name
        self.settings = settings
        security.require_keys_off_loopback(settings)  # SecurityError: said in one line by the CLI
        self.context = context or security.context(settings.curve_keys_dir)
        self.counters: Counter = Counter()
        self.state: ServiceState = "starting"
        self.started = time.monotonic()
        self.details: Callable[[], dict[str, Any]] = dict
        self._errors: list[Callable[[], str | None]] = []
        self._stop_requested = False
        self._readers: dict[zmq.Socket, Callable[[], None]] = {}
        self.poller = zmq.Poller()
        self.control = ControlServer(
            control_endpoint,
            max_message_bytes=settings.max_message_bytes,
            context=self.context,
            counters=self.counters,
        )
        self.control.register("health", lambda args: self.health().model_dump())
        self.add_reader(self.control.socket, self.control.handle_one)
        self.last_error: str | None = None
        # From here on a stop request is honoured, even before run(): a SIGTERM during
        # start-up ends the service cleanly instead of killing it.
        signal.signal(signal.SIGTERM, self.request_stop)
        signal.signal(signal.SIGINT, self.request_stop)

    def add_reader(self, socket: zmq.Socket | int, callback: Callable[[], None]) -> None:
        """Call ``callback`` whenever ``socket`` has a message (or a file descriptor,
        e.g. a pipe a thread writes to, has bytes)."""
        self._readers[socket] = callback
        self.poller.register(socket, zmq.POLLIN)

    def report_errors_from(self, source: Callable[[], str | None]) -> None:
        """Health's ``last_error`` also looks at ``source`` (e.g. a subscriber's), first:
        a condition that holds now outranks the last refused request."""
        self._errors.append(source)

    def error(self, message: str) -> None:
        """Record an error for health and the log; the service keeps running."""
        self.last_error = message
        self.counters["errors"] += 1
        log.error("%s", message)

    def health(self) -> Health:
        # What is wrong now (a lost serial link, a subscriber's) before the last refused
        # request: a stage whose cable was pulled showed an earlier 'owned' refusal.
        errors = [source() for source in self._errors] + [self.last_error, self.control.last_error]
        return Health(
            service=self.name,
            state=self.state,
            pid=os.getpid(),
            uptime_s=round(time.monotonic() - self.started, 3),
            counters=dict(self.counters),
            last_error=next((error for error in errors if error), None),
            details=self.details(),
        )

    @property
    def stopping(self) -> bool:
        """A stop was asked for (work in progress may end early)."""
        return self._stop_requested

    def request_stop(self, signum: int | None = None, frame: Any = None) -> None:
        if signum is not None:
            log.info("received %s, stopping", signal.Signals(signum).name)
        self._stop_requested = True

    def run(self, step: Step | None = None) -> int:
        """Serve until SIGTERM/SIGINT; returns the process exit code."""
        if self.state == "starting":
            self.state = "running"
        log.info("%s ready, control on %s", self.name, self.control.endpoint)
        try:
            while not self._stop_requested:
                wait_s = step() if step else None
                # Wake at least every 200 ms so a stop request is seen promptly.
                timeout_ms = 200 if wait_s is None else max(0, min(200, int(wait_s * 1000)))
                for socket, _ in self.poller.poll(timeout_ms):
                    self._readers[socket]()
        finally:
            self.state = "stopping"
            for socket in list(self._readers):
                if isinstance(socket, zmq.Socket):
                    socket.close(linger=0)
            log.info("%s stopped", self.name)
        return 0


def end_process(code: int) -> NoReturn:
    """End a service's process with exit ``code`` once its ``main`` has returned (its
    sockets, serial port, files and database closed in its own ``finally``), without
    the interpreter's finalization.

    Why: tearing down the modules of a process that has run (numpy, pyzmq, uvicorn,
    numba, their objects) took 0.3-0.9 s after everything was closed, and a stack is
    stopped a group at a time (:data:`semservo.launcher.STOP_ORDER`), so every stop of a
    stack waited seconds for nothing. What finalization would still do is done here:
    threads that are not daemons are joined (as Python joins them at exit), atexit
    handlers run, logs and standard streams are flushed."""
    current = threading.current_thread()
    for thread in threading.enumerate():
        if thread is not current and not thread.daemon:
            thread.join()
    # CPython's own exit runs this: the handlers registered, logging's shutdown among them.
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a closed or broken pipe: nothing left to say there
            stream.flush()
    os._exit(code)
