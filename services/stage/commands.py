"""The stage service's command handlers: each a function of the core and a checked
request (declared in :mod:`semservo.protocol.stage`), testable without a socket."""

from __future__ import annotations

from semservo.protocol import Handlers, NoArguments
from semservo.protocol import stage as protocol
from services.stage.core import StageCore

handlers: Handlers[StageCore] = Handlers(protocol.COMMANDS)


@handlers.handles(protocol.STATE)
def state(core: StageCore, _request: NoArguments) -> protocol.StageState:
    return protocol.StageState.model_validate(core.describe())


def _settles(core: StageCore, reply: dict) -> dict:
    """Keep when the stage will have settled after this command (``state``'s
    ``settled_at_ns``: a teach averages only frames scanned after it)."""
    core.settled_at_ns = max(core.settled_at_ns, int(reply.get("settled_at_ns") or 0))
    return reply


@handlers.handles(protocol.MOVE)
def move(core: StageCore, request: protocol.MoveRequest) -> protocol.MoveReply:
    return protocol.MoveReply.model_validate(_settles(core, core.move(request.targets, relative=request.relative,
                                                                      owner=request.owner)))


@handlers.handles(protocol.ROTATE)
def rotate(core: StageCore, request: protocol.RotateRequest) -> protocol.RotateReply:
    return protocol.RotateReply.model_validate(_settles(core, core.rotate(request.targets, relative=request.relative,
                                                                          owner=request.owner)))


@handlers.handles(protocol.SET_VOLTAGES)
def set_voltages(core: StageCore, request: protocol.SetVoltagesRequest) -> protocol.MoveReply:
    return protocol.MoveReply.model_validate(_settles(core, core.set_voltages(request.voltages, owner=request.owner)))


@handlers.handles(protocol.ARM)
def arm(core: StageCore, request: protocol.ArmRequest) -> protocol.StageState:
    return protocol.StageState.model_validate(core.arm(request.hold_after_s, request.owner))


@handlers.handles(protocol.DISARM)
def disarm(core: StageCore, request: protocol.OwnerRequest) -> protocol.StageState:
    return protocol.StageState.model_validate(core.disarm(request.owner))


@handlers.handles(protocol.HEARTBEAT)
def heartbeat(core: StageCore, request: protocol.OwnerRequest) -> protocol.HeartbeatReply:
    return protocol.HeartbeatReply.model_validate(core.heartbeat(request.owner))


@handlers.handles(protocol.STOP)
def stop(core: StageCore, request: protocol.StopRequest) -> protocol.StageState:
    return protocol.StageState.model_validate(core.stop(request.reason, by="request"))


@handlers.handles(protocol.RESUME)
def resume(core: StageCore, _request: NoArguments) -> protocol.StageState:
    return protocol.StageState.model_validate(core.resume())


@handlers.handles(protocol.RELEASE)
def release(core: StageCore, _request: NoArguments) -> protocol.StageState:
    return protocol.StageState.model_validate(core.release())


@handlers.handles(protocol.LOG)
def log(core: StageCore, request: protocol.LogRequest) -> protocol.LogReply:
    return protocol.LogReply.model_validate({"entries": core.command_log(request.since_ns)})
