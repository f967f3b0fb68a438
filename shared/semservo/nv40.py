"""The piezosystem jena NV 40/3 amplifier's serial protocol: every constant and the
parsing and formatting of its lines, in one place.

Imported by the emulator (``services/fakelab``) and by the real driver (the stage
service), so the two cannot drift apart. Facts from ``shared/reference/nv403-and-tritor.md``
(the vendor's psj-lib, its Micro-Manager adapter, an EPICS driver): where sources
disagree the emulator is strict where they agree and the driver tolerant where they
don't (XON present or not, ``ErrorCode`` or ``ERROR`` replies).

Wire format: 19200 baud, 8N1, commands and replies end with ``\\r``. The device answers
XOFF (0x13) on receipt of a command and XON (0x11) when ready, around any reply text.
"""

from __future__ import annotations

from dataclasses import dataclass

from semservo.instruments import DeviceError

BAUD_RATE = 19200
TERMINATOR = b"\r"
XON = b"\x11"
XOFF = b"\x13"
ENCODING = "ascii"
#: Replies come within 200-500 ms on the real device; clients commonly wait 0.5-0.6 s.
REPLY_TIMEOUT_S = 0.6

CHANNELS = (0, 1, 2)
PROMPT_CLOSED_LOOP_MODEL = "NV403CLE>"
PROMPT_OPEN_LOOP_MODEL = "NV403>"

#: Output voltage range of the amplifier (read the real limits with dspvmin/dspvmax).
VOLTAGE_MIN = -20.0
VOLTAGE_MAX = 130.0
#: Closed-loop travel limits most client code uses (micrometres).
CLOSED_LOOP_MIN_UM = 0.0
CLOSED_LOOP_MAX_UM = 80.0
#: The lab code refuses voltages outside this band (and homes with setall,-20,-20,-20).
LAB_SAFE_VOLTAGE = (-19.0, 110.0)

# Status bits of `stat,<ch>` (STATUS,<ch>,<int>).
STATUS_ACTUATOR_NAME_SET = 0x1
STATUS_SERIAL_SET = 0x2
STATUS_AXIS_SET = 0x4
STATUS_CLOSED_LOOP = 0x8
STATUS_HAS_MEASURING_SYSTEM = 0x10
STATUS_MONITOR_MODE = 0x60
STATUS_REMOTE = 0x80
STATUS_ACTUATOR_READY = 0x8000

# Error codes (the vendor library's ErrorCode,<n> replies).
ERROR_UNKNOWN_COMMAND = 11
ERROR_UNKNOWN_CHANNEL = 15
ERROR_MISSING_PARAMETER = 17
ERROR_OUT_OF_RANGE = 18
ERROR_ACTUATOR_NOT_CONNECTED = 25
ERROR_TEXT = {
    ERROR_UNKNOWN_COMMAND: "unknown command",
    ERROR_UNKNOWN_CHANNEL: "unknown channel",
    16: "unknown channel",
    ERROR_MISSING_PARAMETER: "missing parameter",
    ERROR_OUT_OF_RANGE: "value out of range",
    ERROR_ACTUATOR_NOT_CONNECTED: "actuator not connected",
}

#: Commands the device knows, and how many parameters each takes (possible counts).
COMMANDS: dict[str, tuple[int, ...]] = {
    "setk": (2,),
    "cloop": (1, 2),
    "set": (2,),
    "setall": (3,),
    "rk": (1,),
    "measure": (0,),
    "stat": (1,),
    "dspvmin": (0,),
    "dspvmax": (0,),
    "dspclmin": (1,),
    "dspclmax": (1,),
    "acdescr": (1,),
    "ver": (0,),
}
#: Commands that answer no text (only XOFF ... XON).
SILENT_COMMANDS = frozenset({"setk", "set", "setall"})


class ProtocolError(DeviceError):
    """A line the device rejects; ``code`` is its ErrorCode."""

    def __init__(self, code: int, detail: str = ""):
        super().__init__(f"ErrorCode,{code} ({ERROR_TEXT.get(code, 'error')}{': ' + detail if detail else ''})")
        self.code = code


@dataclass(frozen=True)
class Command:
    name: str
    args: tuple[str, ...]


def format_value(value: float) -> str:
    """Numbers on the wire: three decimals, as the vendor's clients write them."""
    return f"{value:.3f}"


def encode(name: str, *args: float | int | str) -> bytes:
    """A command line, e.g. ``encode("set", 0, 12.5)`` -> ``b"set,0,12.500\\r"``."""
    parts = [name] + [format_value(a) if isinstance(a, float) else str(a) for a in args]
    return ",".join(parts).encode(ENCODING) + TERMINATOR


def parse_command(line: str) -> Command:
    """Split a received command line (without its terminator) into name and arguments.

    Raises :class:`ProtocolError` for an unknown command or a wrong number of arguments.
    """
    fields = [field.strip() for field in line.strip().split(",")]
    name, args = fields[0].lower(), tuple(field for field in fields[1:] if field != "")
    if name not in COMMANDS:
        raise ProtocolError(ERROR_UNKNOWN_COMMAND, name)
    if len(args) not in COMMANDS[name]:
        if len(args) < min(COMMANDS[name]):
            raise ProtocolError(ERROR_MISSING_PARAMETER, name)
        raise ProtocolError(ERROR_UNKNOWN_COMMAND, f"{name} takes {COMMANDS[name]} parameters")
    return Command(name, args)


def parse_channel(text: str) -> int:
    try:
        channel = int(text)
    except ValueError:
        raise ProtocolError(ERROR_UNKNOWN_CHANNEL, text) from None
    if channel not in CHANNELS:
        raise ProtocolError(ERROR_UNKNOWN_CHANNEL, text)
    return channel


def parse_number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ProtocolError(ERROR_OUT_OF_RANGE, text) from None
    if value != value or value in (float("inf"), float("-inf")):
        raise ProtocolError(ERROR_OUT_OF_RANGE, text)
    return value


def strip_flow_control(data: bytes) -> bytes:
    """Reply bytes without XON/XOFF (a driver tolerates them present or absent)."""
    return data.replace(XON, b"").replace(XOFF, b"")


def parse_reply(line: str) -> tuple[str, list[str]]:
    """Split a reply line: ``"rk,0,12.500"`` -> ``("rk", ["0", "12.500"])``. An error
    reply (``ErrorCode,<n>`` or ``ERROR,"..."``) raises :class:`ProtocolError`."""
    fields = [field.strip() for field in line.strip().split(",")]
    if fields[0].lower() == "errorcode":
        raise ProtocolError(int(fields[1]) if len(fields) > 1 and fields[1].isdigit() else 0)
    if fields[0].upper() == "ERROR":
        raise ProtocolError(0, ",".join(fields[1:]).strip('"'))
    return fields[0], fields[1:]
