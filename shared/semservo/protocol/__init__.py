"""Every ZeroMQ command, declared once: its name, a request model, a reply model and one
line of what it does (pydantic v2).

The declarations are shared by the three places that need them:

* the **service** binds each one to a handler, a module-level function
  ``handler(core, request) -> reply`` in its ``commands.py``, through :class:`Handlers`
  (the arguments are checked against the request model before the handler sees them:
  unknown fields, NaN, infinities, a ``true`` where a number belongs are refused as
  ``bad_request`` naming the field);
* its **callers** go through a :class:`Port`: :class:`ServicePort` over the service's
  control socket (lazy pirate, :class:`semservo.transport.ControlClient`), or
  :class:`LocalPort` in the same process, through the same handlers (for tests of a
  core that talks to another core without sockets);
* the **docs**: ``docs/architecture.md``'s command tables are generated from these
  declarations (:func:`markdown`, ``python -m semservo.protocol``), and a test checks they
  match.

A refusal is :class:`semservo.errors.CommandError` everywhere: raised by a handler, carried
by the reply, raised again by the port.

Modules: :mod:`.stage`, :mod:`.controller`, :mod:`.estimator`, :mod:`.imageserver`,
:mod:`.fakelab`; :data:`HEALTH` is answered by every service.
"""

from __future__ import annotations

import json
import threading
from dataclasses import dataclass
from typing import Any, Callable, Generic, Iterator, Protocol, TypeVar

import pydantic
from pydantic import BaseModel, ConfigDict

from semservo.errors import BadRequest, describe_validation_error
from semservo.messages import Health

__all__ = ["HEALTH", "Command", "CommandReply", "CommandRequest", "CommandSet", "Handlers", "LocalPort", "NoArguments",
           "Port", "ServicePort", "carryable_text", "markdown"]


def carryable_text(text: str, max_chars: int) -> tuple[str, list[str]]:
    """``text`` as a request's string field carries it, and what was changed: code points
    that are not text (a lone surrogate: valid JSON, not UTF-8) replaced, white space
    made single spaces, cut to ``max_chars`` (its last one an ellipsis). For what must
    never be refused for its wording (a stop's reason)."""
    changed = []
    cleaned = text.encode("utf-8", "replace").decode("utf-8")
    if cleaned != text:
        changed.append("characters that are not text replaced")
    cleaned = " ".join(cleaned.split())
    if len(cleaned) > max_chars:
        cleaned = cleaned[:max_chars - 1] + "…"
        changed.append(f"cut to {max_chars} characters")
    return cleaned, changed


class CommandRequest(BaseModel):
    """Base of every request: unknown fields, NaN, infinity and a value of another JSON
    type (``true`` is not 1, ``"2"`` is not 2) are refused."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True, frozen=True)


class CommandReply(BaseModel):
    """Base of every reply (what a handler returns and a port hands back)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    def __getitem__(self, key: str) -> Any:
        """``reply["state"]`` as well as ``reply.state``: scripts written against the
        dictionaries replies used to be keep working."""
        try:
            return getattr(self, key)
        except AttributeError:
            raise KeyError(key) from None

    def get(self, key: str, default: Any = None) -> Any:
        return getattr(self, key, default)

    def keys(self):
        return self.model_dump().keys()

    def __contains__(self, key: str) -> bool:
        return key in type(self).model_fields or key in (self.model_extra or {})

    def __eq__(self, other: Any) -> bool:
        if isinstance(other, dict):  # a reply compares as the dictionary it was
            return self.model_dump() == other
        return super().__eq__(other)

    __hash__ = None  # mutable, as dictionaries are


class NoArguments(CommandRequest):
    """A command that takes nothing."""


class OpenReply(CommandReply):
    """A reply whose fields are the service's own description (passed through as they are)."""

    model_config = ConfigDict(extra="allow", allow_inf_nan=False)


RequestT = TypeVar("RequestT", bound=BaseModel)
ReplyT = TypeVar("ReplyT", bound=BaseModel)


@dataclass(frozen=True)
class Command(Generic[RequestT, ReplyT]):
    """One command of one service: ``name`` on the wire, what it takes and answers."""

    service: str
    name: str
    request: type[RequestT]
    reply: type[ReplyT]
    summary: str
    #: Commands that work before they answer (a teach plans FFTs, a record carries every
    #: iteration) get longer than a port's default timeout.
    timeout_s: float | None = None

    def parse(self, args: dict[str, Any] | None) -> RequestT:
        """The request from a message's arguments, checked as JSON (the wire's own form)."""
        try:
            return self.request.model_validate_json(json.dumps(args or {}, allow_nan=True))
        except pydantic.ValidationError as error:
            raise BadRequest(describe_validation_error(error, "arguments")) from None

    def build(self, request: RequestT | None = None, **fields: Any) -> RequestT:
        """A request from Python values (a caller's), checked the same way."""
        if request is not None:
            if fields:
                raise TypeError("give a request model or fields, not both")
            return request
        try:
            return self.request.model_validate(fields, strict=False)
        except pydantic.ValidationError as error:
            raise BadRequest(describe_validation_error(error, "arguments")) from None


HEALTH: Command[NoArguments, Health] = Command("*", "health", NoArguments, Health,
                                               "state, pid, uptime, counters, last error, details")


class CommandSet:
    """The commands of one service, in the order a reader meets them."""

    def __init__(self, service: str, summary: str):
        self.service = service
        self.summary = summary
        self._commands: dict[str, Command] = {"health": HEALTH}

    def add(self, name: str, request: type[RequestT], reply: type[ReplyT], summary: str,
            *, timeout_s: float | None = None) -> Command[RequestT, ReplyT]:
        if name in self._commands:
            raise ValueError(f"{self.service} declares {name!r} twice")
        command = Command(self.service, name, request, reply, summary, timeout_s)
        self._commands[name] = command
        return command

    def __iter__(self) -> Iterator[Command]:
        return iter(self._commands.values())

    def __getitem__(self, name: str) -> Command:
        return self._commands[name]

    def __contains__(self, name: str) -> bool:
        return name in self._commands

    def names(self) -> list[str]:
        return list(self._commands)


CoreT = TypeVar("CoreT")
Handler = Callable[[Any, Any], BaseModel]


class Handlers(Generic[CoreT]):
    """A service's handlers: module-level functions ``(core, request) -> reply``, one per
    declared command (``health`` is the runtime's own)."""

    def __init__(self, commands: CommandSet):
        self.commands = commands
        self._handlers: dict[str, Handler] = {}

    def handles(self, command: Command[RequestT, ReplyT]) -> Callable[[Callable[[CoreT, RequestT], ReplyT]],
                                                                       Callable[[CoreT, RequestT], ReplyT]]:
        """Decorator: this function answers ``command``."""
        if command.name not in self.commands or self.commands[command.name] is not command:
            raise ValueError(f"{command.name!r} is not a command of {self.commands.service}")

        def register(function):
            self._handlers[command.name] = function
            return function

        return register

    def missing(self) -> list[str]:
        """Declared commands without a handler (a test keeps this empty)."""
        return [name for name in self.commands.names() if name != "health" and name not in self._handlers]

    def call(self, core: CoreT, command: Command[RequestT, ReplyT], request: RequestT) -> ReplyT:
        """Run one handler on a request already checked; the reply checked against its model."""
        reply = self._handlers[command.name](core, request)
        if not isinstance(reply, command.reply):
            reply = command.reply.model_validate(reply)
        return reply

    def dispatch(self, core: CoreT, name: str, args: dict[str, Any] | None) -> dict[str, Any]:
        """A message's command, from its raw arguments to the reply's JSON form (what the
        control socket sends back)."""
        command = self.commands[name]
        return self.call(core, command, command.parse(args)).model_dump(mode="json")

    def bind(self, server, core: CoreT) -> None:
        """Register every handler on a :class:`semservo.transport.ControlServer`."""
        for name in self._handlers:
            server.register(name, lambda args, name=name: self.dispatch(core, name, args))


class Port(Protocol):
    """How a core talks to another service: typed calls that return the reply model or
    raise :class:`~semservo.errors.CommandError` /
    :class:`~semservo.errors.ServiceUnavailable`."""

    def call(self, command: Command[RequestT, ReplyT], request: RequestT | None = None, /,
             **fields: Any) -> ReplyT: ...


class ServicePort:
    """A service's control socket as typed calls (``port.call(stage.MOVE, targets=...)``),
    over a lazy-pirate :class:`~semservo.transport.ControlClient`.

    ``shared``: one request at a time from many threads (a ZeroMQ socket serves one).
    ``timeouts``: per-command timeouts over the commands' own (seconds).
    """

    def __init__(self, client, *, shared: bool = False, timeouts: dict[str, float] | None = None):
        self.client = client
        self.timeouts = timeouts or {}
        self._lock = threading.Lock() if shared else None

    @property
    def endpoint(self) -> str:
        return self.client.endpoint

    def call(self, command: Command[RequestT, ReplyT], request: RequestT | None = None, /,
             **fields: Any) -> ReplyT:
        built = command.build(request, **fields)
        result = self.raw(command.name, built.model_dump(mode="json"),
                          timeout_s=self.timeouts.get(command.name, command.timeout_s))
        return command.reply.model_validate(result)

    def raw(self, name: str, args: dict[str, Any], *, timeout_s: float | None = None) -> dict[str, Any]:
        """An untyped request (fault campaigns and tests of malformed arguments)."""
        if self._lock is None:
            return self.client.request(name, timeout_s=timeout_s, **args)
        with self._lock:
            return self.client.request(name, timeout_s=timeout_s, **args)

    def close(self) -> None:
        if self._lock is None:
            self.client.close()
            return
        with self._lock:
            self.client.close()


class LocalPort(Generic[CoreT]):
    """Another core in this process, through its service's handlers: the same checks,
    refusals and replies as over its socket, without one."""

    def __init__(self, handlers: Handlers[CoreT], core: CoreT):
        self.handlers = handlers
        self.core = core

    def call(self, command: Command[RequestT, ReplyT], request: RequestT | None = None, /,
             **fields: Any) -> ReplyT:
        built = command.build(request, **fields)
        reply = self.handlers.call(self.core, command, command.parse(built.model_dump(mode="json")))
        # What crosses a socket is JSON: hand back what the far side would read.
        return command.reply.model_validate(reply.model_dump(mode="json"))


# -- docs -----------------------------------------------------------------------------------
def _schema_text(schema: dict, defs: dict) -> str:
    """A JSON schema as a few words for a table cell: ``number (> 0, <= 1e+06) or null``."""
    if "$ref" in schema:
        return schema["$ref"].rsplit("/", 1)[-1]
    if "anyOf" in schema:
        return " or ".join(dict.fromkeys(_schema_text(part, defs) for part in schema["anyOf"]))
    if "enum" in schema:
        return " / ".join(json.dumps(value) for value in schema["enum"])
    if "const" in schema:
        return json.dumps(schema["const"])
    kind = schema.get("type", "any")
    if kind == "array":
        kind = f"list of {_schema_text(schema.get('items', {}), defs)}"
    elif kind == "object":
        values = schema.get("additionalProperties")
        kind = f"object of {_schema_text(values, defs)}" if isinstance(values, dict) else "object"
    bounds = [f"{sign} {schema[key]:g}" for key, sign in (("exclusiveMinimum", ">"), ("minimum", ">="),
                                                         ("exclusiveMaximum", "<"), ("maximum", "<="))
              if key in schema]
    if schema.get("minItems") is not None and schema.get("minItems") == schema.get("maxItems"):
        bounds.append(f"{schema['minItems']} items")
    else:
        bounds += [f"{what} {schema[key]} items" for key, what in (("minItems", "at least"), ("maxItems", "at most"))
                   if key in schema]
    return kind + (f" ({', '.join(bounds)})" if bounds else "")


def fields_text(model: type[BaseModel]) -> str:
    """``name: type = default`` of a model's fields, for the docs."""
    if model is NoArguments:
        return "-"
    schema = model.model_json_schema()
    defs = schema.get("$defs", {})
    parts = []
    for name, info in model.model_fields.items():
        text = _schema_text(schema.get("properties", {}).get(name, {}), defs)
        default = "" if info.is_required() else f" = {json.dumps(info.get_default(call_default_factory=True), default=str)}"
        parts.append(f"`{name}`: {text}{default}")
    open_ended = model.model_config.get("extra") == "allow"
    if not parts:
        return "the service's own description" if open_ended else "-"
    return "; ".join(parts) + (" (and the service's own fields)" if open_ended else "")


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def markdown(command_sets: list[CommandSet] | None = None) -> str:
    """The command tables of ``docs/architecture.md``, generated from the declarations."""
    if command_sets is None:
        from semservo.protocol import controller, estimator, fakelab, imageserver, stage

        command_sets = [fakelab.COMMANDS, imageserver.COMMANDS, estimator.COMMANDS, stage.COMMANDS,
                        controller.COMMANDS]
    lines = []
    for commands in command_sets:
        lines += [f"#### {commands.service}", "", commands.summary, "",
                  "| command | request | reply | what it does |", "| --- | --- | --- | --- |"]
        for command in commands:
            if command.name == "health":
                continue
            lines.append(f"| `{command.name}` | {_cell(fields_text(command.request))} | `{command.reply.__name__}`: "
                         f"{_cell(fields_text(command.reply))} | {_cell(command.summary)} |")
        lines.append("")
    lines.append("Every service also answers `health` → `Health {service, state, pid, uptime_s, counters, "
                 "last_error, details}`.")
    return "\n".join(lines) + "\n"
