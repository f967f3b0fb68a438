"""Connect the emulated NV 40/3 to the outside: a pseudo-terminal (a real serial device
path for pyserial, like /dev/ttyUSB0) and a TCP port (pyserial's socket://host:port, for
containers). Each link has its own line buffer; all share the device's state.

Both links share a ``plugged`` event: clearing it pulls the cable. The device then
answers nothing on the pseudo-terminal and the TCP connections drop (new ones are
closed at once), which is what a driver sees when a serial cable or USB adapter is
pulled."""

from __future__ import annotations

import contextlib
import logging
import os
import select
import socket
import threading
import tty

from services.fakelab.emulator import NV403Emulator

log = logging.getLogger("fakelab.serial")


def _plugged() -> threading.Event:
    plugged = threading.Event()
    plugged.set()
    return plugged


class PseudoTerminalLink:
    """The device on a pseudo-terminal; ``path`` is what a driver opens."""

    def __init__(self, make_emulator, plugged: threading.Event | None = None):
        self.plugged = plugged if plugged is not None else _plugged()
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no line discipline: CR stays CR, no echo
        self.path = os.ttyname(self.slave)
        self.emulator: NV403Emulator = make_emulator()
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, name="nv403-pty", daemon=True)

    def start(self) -> "PseudoTerminalLink":
        self.thread.start()
        return self

    def _serve(self) -> None:
        while not self._stop.is_set():
            readable, _, _ = select.select([self.master], [], [], 0.1)
            if not readable:
                continue
            try:
                data = os.read(self.master, 1024)
            except OSError:
                continue  # no client has the port open right now
            if not self.plugged.is_set():
                continue  # the cable is out: bytes go nowhere
            reply = self.emulator.feed(data)
            if reply:
                os.write(self.master, reply)

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(timeout=1)
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):  # already closed
                os.close(fd)


class TcpLink:
    """The device on a TCP port, one emulator line buffer per connection."""

    def __init__(self, make_emulator, host: str, port: int, plugged: threading.Event | None = None):
        self.plugged = plugged if plugged is not None else _plugged()
        self.make_emulator = make_emulator
        self.server = socket.create_server((host, port), reuse_port=False)
        self.server.settimeout(0.1)
        self.host, self.port = self.server.getsockname()[:2]
        self.url = f"socket://{self.host}:{self.port}"
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._accept, name="nv403-tcp", daemon=True)

    def start(self) -> "TcpLink":
        self.thread.start()
        return self

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                connection, peer = self.server.accept()
            except (TimeoutError, socket.timeout):
                continue
            except OSError:
                return
            if not self.plugged.is_set():
                connection.close()
                continue
            log.info("serial client connected over TCP from %s", peer)
            threading.Thread(target=self._serve, args=(connection,), daemon=True).start()

    def _serve(self, connection: socket.socket) -> None:
        emulator = self.make_emulator()
        connection.settimeout(0.2)
        with connection:
            while not self._stop.is_set():
                if not self.plugged.is_set():
                    return  # pulled: the connection drops
                try:
                    data = connection.recv(1024)
                except (TimeoutError, socket.timeout):
                    continue
                except OSError:
                    return
                if not data:
                    return
                reply = emulator.feed(data)
                if reply:
                    connection.sendall(reply)

    def stop(self) -> None:
        self._stop.set()
        self.server.close()
        self.thread.join(timeout=1)
