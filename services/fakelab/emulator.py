"""The NV 40/3 amplifier, emulated: bytes in, bytes out, against the world's piezo axes.

Strict where the sources agree (``semservo.nv40``): commands end with CR, every command
is answered XOFF ... XON around its reply text, errors are ``ErrorCode,<n>``, a bare CR
answers the prompt. ``set`` is ignored while a channel is under front-panel (knob)
control and ``setall`` unless all three are remote, as on the device.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from semservo import nv40
from semservo.simulation.world import World

FIRMWARE = ("NV40/3CLE V5.09", "date: 2012-03-14", "serial no.: 10112")
ACTUATOR = "TRITOR100"


@dataclass
class ChannelState:
    remote: bool = False
    closed_loop: bool = False
    knob_voltage: float = 0.0  # what the front panel would set


@dataclass
class NV403Emulator:
    world: World
    prompt: str = nv40.PROMPT_CLOSED_LOOP_MODEL
    channels: dict = field(default_factory=lambda: {c: ChannelState() for c in nv40.CHANNELS})
    buffer: bytes = b""
    log: list = field(default_factory=list)

    def __post_init__(self):
        for channel in nv40.CHANNELS:
            if not self.channels[channel].remote:
                self.channels[channel].knob_voltage = self.world.voltage(channel)

    def feed(self, data: bytes) -> bytes:
        """Bytes from the host in; the bytes the device sends back."""
        self.buffer += data
        out = b""
        while nv40.TERMINATOR in self.buffer:
            line, self.buffer = self.buffer.split(nv40.TERMINATOR, 1)
            out += self.handle(line.decode(nv40.ENCODING, errors="replace"))
        if len(self.buffer) > 256:  # a runaway line without CR: the device drops it
            self.buffer = b""
            out += self._reply([f"ErrorCode,{nv40.ERROR_UNKNOWN_COMMAND}"])
        return out

    @staticmethod
    def _reply(lines: list[str]) -> bytes:
        text = b"".join(line.encode(nv40.ENCODING) + nv40.TERMINATOR for line in lines)
        return nv40.XOFF + text + nv40.XON

    def handle(self, line: str) -> bytes:
        line = line.strip(nv40.XON.decode() + nv40.XOFF.decode() + " \n")
        if not line:
            return self.prompt.encode(nv40.ENCODING)
        try:
            lines = self.execute(nv40.parse_command(line))
        except nv40.ProtocolError as error:
            lines = [f"ErrorCode,{error.code}"]
        self.log.append((line, lines))
        return self._reply(lines)

    def _output_voltage(self, channel: int) -> float:
        return self.world.voltage(channel)

    def execute(self, command: nv40.Command) -> list[str]:
        name, args = command.name, command.args
        fmt = nv40.format_value
        if name == "ver":
            return list(FIRMWARE)
        if name == "measure":
            return ["aw," + ",".join(fmt(self._output_voltage(c)) for c in nv40.CHANNELS)]
        if name == "dspvmin":
            return [f"dspvmin,{fmt(nv40.VOLTAGE_MIN)}"]
        if name == "dspvmax":
            return [f"dspvmax,{fmt(nv40.VOLTAGE_MAX)}"]
        if name == "setall":
            values = [nv40.parse_number(a) for a in args]
            for value in values:
                self._check_voltage(value)
            if all(self.channels[c].remote for c in nv40.CHANNELS):
                for channel, value in zip(nv40.CHANNELS, values):
                    self.world.set_voltage(channel, value)
            return []
        channel = nv40.parse_channel(args[0])
        state = self.channels[channel]
        if name == "setk":
            flag = self._flag(args[1])
            if not flag and state.remote:
                state.knob_voltage = self._output_voltage(channel)
            state.remote = flag
            return []
        if name == "cloop":
            if len(args) == 1:
                return [f"cloop,{channel},{int(state.closed_loop)}"]
            self._flag(args[1])  # accepted, but an actuator without a sensor stays open loop
            return []
        if name == "set":
            value = nv40.parse_number(args[1])
            self._check_voltage(value)
            if state.remote:  # ignored under front-panel control, as on the device
                self.world.set_voltage(channel, value)
            return []
        if name == "rk":
            return [f"rk,{channel},{fmt(self._output_voltage(channel))}"]
        if name == "stat":
            bits = (nv40.STATUS_ACTUATOR_NAME_SET | nv40.STATUS_SERIAL_SET | nv40.STATUS_AXIS_SET
                    | nv40.STATUS_ACTUATOR_READY | (nv40.STATUS_REMOTE if state.remote else 0))
            return [f"STATUS,{channel},{bits}"]
        if name == "dspclmin":
            return [f"dspclmin,{channel},{fmt(nv40.CLOSED_LOOP_MIN_UM)}"]
        if name == "dspclmax":
            return [f"dspclmax,{channel},{fmt(nv40.CLOSED_LOOP_MAX_UM)}"]
        if name == "acdescr":
            return [f"acdescr,{channel},{ACTUATOR}"]
        raise nv40.ProtocolError(nv40.ERROR_UNKNOWN_COMMAND, name)  # pragma: no cover - COMMANDS guards

    @staticmethod
    def _flag(text: str) -> bool:
        if text not in ("0", "1"):
            raise nv40.ProtocolError(nv40.ERROR_OUT_OF_RANGE, text)
        return text == "1"

    @staticmethod
    def _check_voltage(value: float) -> None:
        if not nv40.VOLTAGE_MIN <= value <= nv40.VOLTAGE_MAX:
            raise nv40.ProtocolError(nv40.ERROR_OUT_OF_RANGE, nv40.format_value(value))
