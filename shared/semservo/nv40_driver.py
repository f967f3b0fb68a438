"""Driver for the NV 40/3 piezo amplifier over RS-232 (pyserial), the real device or the
fake lab's emulator: the same code opens ``/dev/ttyUSB0``, a pseudo-terminal path or a
``socket://host:port`` URL.

The protocol itself lives in :mod:`semservo.nv40` (shared with the emulator). The driver
is tolerant where the sources disagree: it accepts replies with or without XON/XOFF
framing and both error styles. Set-point commands give no read-back on the device, so
:meth:`NV403Driver.set_voltage` verifies with ``rk`` and reports what the amplifier
actually outputs. Every line sent and received is kept, with its time, for run records.
"""

from __future__ import annotations

import threading
import time
from typing import Callable

import serial

from semservo import nv40
from semservo.instruments import LinkError, LogEntry

try:
    import termios

    _TERMINAL_ERRORS: tuple[type[BaseException], ...] = (termios.error,)
except ImportError:  # not POSIX: pyserial raises its own
    _TERMINAL_ERRORS = ()

#: What a port raises when its device goes away: pyserial's error, the OS's, and termios's
#: (a pulled USB adapter or a closed pseudo-terminal fails tcflush with EIO as a
#: termios.error, which is neither, and once took the whole stage service down).
LINK_FAILURES: tuple[type[BaseException], ...] = (serial.SerialException, OSError, *_TERMINAL_ERRORS)

__all__ = ["LinkError", "LogEntry", "NV403Driver"]


class NV403Driver:
    """One NV 40/3 on one serial link. Thread-safe: one transaction at a time.

    A :class:`semservo.instruments.StageDriver` (outputs in volts, channels 0-2) for
    the stage service, and the NV 40/3's own commands for scripts and tests.
    """

    def __init__(self, port: serial.SerialBase, *, reply_timeout_s: float = nv40.REPLY_TIMEOUT_S,
                 log_limit: int = 10_000):
        self.port = port
        self.reply_timeout_s = reply_timeout_s
        self.log: list[LogEntry] = []
        self.log_limit = log_limit
        #: Called with every entry as it is logged (the stage service keeps them on disk).
        self.on_entry: Callable[[LogEntry], None] | None = None
        self._lock = threading.Lock()

    @classmethod
    def open(cls, url: str, **options) -> "NV403Driver":
        """Open ``url`` (a device path, pseudo-terminal or ``socket://host:port``)."""
        try:
            port = serial.serial_for_url(
                url, baudrate=nv40.BAUD_RATE, bytesize=serial.EIGHTBITS, parity=serial.PARITY_NONE,
                stopbits=serial.STOPBITS_ONE, xonxoff=False, timeout=0.02,
            )
        except (*LINK_FAILURES, ValueError) as error:
            raise LinkError(f"cannot open {url}: {error}") from None
        return cls(port, **options)

    def close(self) -> None:
        try:
            self.port.close()
        except LINK_FAILURES:
            pass  # a port whose device went away is closed as far as it can be

    # -- transactions ---------------------------------------------------------------
    def _record(self, direction: str, text: str) -> None:
        entry = LogEntry(time.time_ns(), direction, text)
        self.log.append(entry)
        if self.on_entry is not None:
            self.on_entry(entry)
        if len(self.log) > self.log_limit:
            del self.log[: len(self.log) - self.log_limit]

    def _read_reply(self, expect_lines: int) -> list[str]:
        """Read until XON, or until ``expect_lines`` lines arrived and the line is quiet
        (devices that do not send XON), or the timeout."""
        received = b""
        deadline = time.monotonic() + self.reply_timeout_s
        while time.monotonic() < deadline:
            chunk = self.port.read(self.port.in_waiting or 1)
            if chunk:
                received += chunk
                if nv40.XON in chunk:
                    break
                continue
            lines = [line for line in nv40.strip_flow_control(received).split(nv40.TERMINATOR) if line]
            if received and len(lines) >= expect_lines and received.endswith(nv40.TERMINATOR):
                break
        else:
            if expect_lines:
                raise LinkError(f"no reply from the amplifier within {self.reply_timeout_s:g} s")
        text = nv40.strip_flow_control(received).decode(nv40.ENCODING, errors="replace")
        lines = [line.strip() for line in text.split(nv40.TERMINATOR.decode()) if line.strip()]
        for line in lines:
            self._record("received", line)
        return lines

    def transact(self, name: str, *args, expect_lines: int = 0) -> list[str]:
        """Send one command; return its reply lines. Raises :class:`nv40.ProtocolError`
        for an error reply and :class:`LinkError` when the link fails."""
        command = nv40.encode(name, *args)
        with self._lock:
            try:
                self.port.reset_input_buffer()
                self.port.write(command)
                self._record("sent", command.decode(nv40.ENCODING).strip())
                lines = self._read_reply(expect_lines)
            except LINK_FAILURES as error:
                raise LinkError(f"serial link failed: {error}") from None
        for line in lines:
            nv40.parse_reply(line)  # raises on ErrorCode / ERROR
        return lines

    def _value(self, name: str, *args) -> list[str]:
        reply = self.transact(name, *args, expect_lines=1)
        if not reply:
            raise LinkError(f"{name}: empty reply")
        return nv40.parse_reply(reply[-1])[1]

    # -- the device --------------------------------------------------------------------
    def identify(self) -> dict:
        """Flush stale bytes (CR twice, as the vendor's clients do), read the prompt and
        the firmware lines."""
        with self._lock:
            try:
                self.port.reset_input_buffer()
                self.port.write(nv40.TERMINATOR * 2)
                deadline = time.monotonic() + self.reply_timeout_s
                prompt = b""
                while time.monotonic() < deadline and not prompt.endswith(b">"):
                    prompt += self.port.read(self.port.in_waiting or 1)
            except LINK_FAILURES as error:
                raise LinkError(f"serial link failed: {error}") from None
        if not prompt.endswith(b">"):
            raise LinkError("no prompt from the amplifier: is it an NV 40/3 and switched on?")
        # Two CRs give two prompts ("NV403CLE>NV403CLE>"): the model is the last one.
        text = nv40.strip_flow_control(prompt).decode(nv40.ENCODING).strip()
        model = text[text.rstrip(">").rfind(">") + 1:] if text.count(">") > 1 else text
        firmware = self.transact("ver", expect_lines=3)
        return {"model": model, "prompt": model, "firmware": firmware}

    def set_remote(self, channel: int, remote: bool = True) -> None:
        """Serial control of ``channel`` (True) or the front-panel knob (False)."""
        self.transact("setk", channel, int(remote))

    def release(self, channels: list[int] | None = None) -> None:
        """Give these channels (default: every one) back to the front panel."""
        for channel in nv40.CHANNELS if channels is None else channels:
            self.set_remote(channel, False)

    def voltage_limits(self) -> tuple[float, float]:
        return float(self._value("dspvmin")[0]), float(self._value("dspvmax")[0])

    def status(self, channel: int) -> int:
        return int(self._value("stat", channel)[1])

    def is_remote(self, channel: int) -> bool:
        return bool(self.status(channel) & nv40.STATUS_REMOTE)

    def read_voltage(self, channel: int) -> float:
        return float(self._value("rk", channel)[1])

    def read_voltages(self) -> tuple[float, float, float]:
        values = self._value("measure")
        return tuple(float(v) for v in values[:3])

    def set_voltage(self, channel: int, volts: float) -> float:
        """Write a set point and read back what the amplifier outputs (the device gives
        no read-back of its own). Returns the read-back voltage."""
        self.transact("set", channel, float(volts))
        return self.read_voltage(channel)

    def set_voltages(self, volts: tuple[float, float, float]) -> tuple[float, float, float]:
        """All three channels at once (the device ignores it unless all are remote)."""
        self.transact("setall", *(float(v) for v in volts))
        return self.read_voltages()

    def set_channels(self, volts: dict[int, float]) -> tuple[float, float, float]:
        """Write several set points (one ``set`` each, the first written at once), then
        read all outputs back with one ``measure``."""
        for channel, value in volts.items():
            self.transact("set", channel, float(value))
        return self.read_voltages()

    # -- the stage driver interface (semservo.instruments.StageDriver) ---------------------
    def take_control(self, channels: list[int]) -> None:
        for channel in channels:
            self.set_remote(channel, True)

    def output_limits(self) -> tuple[float, float]:
        return self.voltage_limits()

    def read_outputs(self) -> dict[int, float]:
        return dict(enumerate(self.read_voltages()))

    def write_outputs(self, values: dict[int, float]) -> dict[int, float]:
        return dict(enumerate(self.set_channels(values)))

    def halt(self) -> None:
        """An open-loop amplifier holds its outputs: there is no motion to stop."""
