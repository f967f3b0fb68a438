"""What every in-memory simulated driver shares (:class:`InMemoryDriver`): devices
kept per URL (a reconnect finds the device as it was, as real hardware keeps its state),
a pulled cable as a :class:`~semservo.instruments.LinkError`, and the exchange log a
real driver keeps of its serial lines.

A device class is a dataclass with ``plugged`` and ``lock``; a driver names its device
class and what it is called, and gets ``open``, ``_exchange``, ``log`` and ``on_entry``.
"""

from __future__ import annotations

import time
from typing import Any, Callable, ClassVar

from semservo.instruments import LinkError, LogEntry


class InMemoryDriver:
    """The connection side of a simulated driver. Subclasses set ``device_type`` (the
    device's dataclass), ``what`` (as it appears in messages and the log, e.g.
    ``"simulated amplifier"``) and a ``devices`` dict of their own (so two kinds of
    device never share a URL's entry)."""

    device_type: ClassVar[type]
    what: ClassVar[str]
    devices: ClassVar[dict[str, Any]]

    def __init__(self, device):
        self.device = device
        self.log: list[LogEntry] = []
        self.on_entry: Callable[[LogEntry], None] | None = None

    @classmethod
    def open(cls, url: str):
        device = cls.devices.setdefault(url, cls.device_type())
        if not device.plugged:
            raise LinkError(f"cannot open {url}: the {cls.what} is unplugged")
        return cls(device)

    def _exchange(self, sent: str, received: str) -> None:
        if not self.device.plugged:
            raise LinkError(f"the {self.what} is unplugged")
        for direction, text in (("sent", sent), ("received", received)):
            entry = LogEntry(time.time_ns(), direction, text)
            self.log.append(entry)
            if self.on_entry is not None:
                self.on_entry(entry)
