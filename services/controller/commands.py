"""The controller's command handlers (declared in :mod:`semservo.protocol.controller`):
functions of a :class:`Controller` (the core and its estimator port) and a checked
request, testable without a socket."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from semservo.errors import CommandError, ServiceUnavailable
from semservo.protocol import Handlers, NoArguments, Port
from semservo.protocol import controller as protocol
from semservo.protocol import estimator as estimator_protocol
from services.controller.core import ControllerCore


@dataclass
class Controller:
    """What the handlers work on: the core, and the estimator (asked for its reference
    when a run starts) with the runs folder (for ``run {id}``'s message)."""

    core: ControllerCore
    estimator: Port
    runs_dir: Path | None = None


handlers: Handlers[Controller] = Handlers(protocol.COMMANDS)


@handlers.handles(protocol.START)
def start(controller: Controller, settings: protocol.RunSettings) -> protocol.ControllerStatus:
    core = controller.core
    if core.state == "servoing":
        raise CommandError("busy", f"run {core.run.id} is active; stop it first")
    try:
        report = controller.estimator.call(estimator_protocol.REPORT)
    except (ServiceUnavailable, CommandError) as error:
        raise CommandError("estimator_unavailable", f"cannot ask the estimator for its reference: {error}") from None
    if report.reference is None:
        raise CommandError("no_reference", "teach a reference first: the estimator has none")
    try:
        return protocol.ControllerStatus.model_validate(core.start(settings, report.reference.model_dump()))
    except ServiceUnavailable as error:
        raise CommandError("stage_unavailable", f"the stage service is unreachable: {error}") from None


@handlers.handles(protocol.STOP)
def stop(controller: Controller, request: protocol.StopRequest) -> protocol.ControllerStatus:
    return protocol.ControllerStatus.model_validate(controller.core.stop(request.reason))


@handlers.handles(protocol.STATUS)
def status(controller: Controller, _request: NoArguments) -> protocol.ControllerStatus:
    return protocol.ControllerStatus.model_validate(controller.core.status())


@handlers.handles(protocol.RUN)
def run(controller: Controller, request: protocol.RunRequest) -> protocol.RunRecord:
    if request.id is None:
        return protocol.RunRecord.model_validate(controller.core.record())
    record = controller.core.stored(request.id)
    if record is None:
        raise CommandError("no_such_run", f"no finished run {request.id!r} in {controller.runs_dir}")
    return protocol.RunRecord.model_validate(record)
