"""Moving the stage by hand: jog, turn, click to move, resume; its state."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from semservo.api import CenterRequest, MoveReply, MoveRequest, RotateReply, RotateRequest, StageState
from semservo.errors import BadRequest
from services.gateway.api.deps import Core, require_token

router = APIRouter(prefix="/stage", tags=["stage"])


@router.post("/move", response_model=MoveReply, dependencies=[Depends(require_token)],
             summary="Jog (relative) or move (absolute), um",
             description="Both of the stage's soft limits apply (GET /stage's `limits`): the travel (model "
                         "displacement) and the amplifier's voltages. Near the ends of travel the voltage a position "
                         "needs depends on the piezo's hysteresis branch, so a target inside the travel may still be "
                         "refused (409 `voltage_limit`, saying the voltage): refused whole, never clipped.")
def move(body: MoveRequest, core: Core) -> MoveReply:
    targets = {axis: value for axis, value in (("x", body.x_um), ("y", body.y_um)) if value is not None}
    if not targets:
        raise BadRequest("give x_um and/or y_um", field="x_um")
    return core.move(targets, body.relative)


@router.post("/rotate", response_model=RotateReply, dependencies=[Depends(require_token)],
             summary="Turn or tilt the rotation-and-tilt stage, degrees (through the stage service's rules)")
def rotate(body: RotateRequest, core: Core) -> RotateReply:
    targets = {axis: value for axis in ("rotation_deg", "tilt_x_deg", "tilt_y_deg")
               if (value := getattr(body, axis)) is not None}
    if not targets:
        raise BadRequest("give rotation_deg, tilt_x_deg and/or tilt_y_deg", field="rotation_deg")
    return core.rotate(targets, body.relative)


@router.post("/center", response_model=MoveReply, dependencies=[Depends(require_token)],
             summary="Click to move: bring this point of the live image to its centre")
def center(body: CenterRequest, core: Core) -> MoveReply:
    return core.center(body.x_px, body.y_px)


@router.post("/resume", response_model=StageState, dependencies=[Depends(require_token)],
             summary="Let a stopped (or watchdog-held) stage move again")
def resume(core: Core) -> StageState:
    return core.resume()


@router.get("", response_model=StageState, summary="Position, voltages, limits, serial link and rotation stage")
def stage(core: Core) -> StageState:
    return core.stage_state()
