"""Stored targets: a taught view kept under a name with the stage's pose and the
acquisition it was taught at, to come back to days later; exported and imported as one
file."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, File, Form, Query, Request, UploadFile
from fastapi.responses import Response

from semservo.api import GoToTarget, StartResult, Target, TargetRequest
from services.gateway.api.deps import Core, require_token
from services.gateway.api.teach import read_upload
from services.gateway.core import to_png

router = APIRouter(prefix="/targets", tags=["targets"])


@router.post("", response_model=Target, status_code=201, dependencies=[Depends(require_token)],
             summary="Store the taught reference under a name, with the stage's pose and the acquisition")
def save(body: TargetRequest, core: Core) -> Target:
    return Target.model_validate(core.save_target(body.name, body.note, body.replace))


@router.get("", response_model=list[Target], summary="Every stored target, newest first")
def targets(core: Core) -> list[Target]:
    return [Target.model_validate(target) for target in core.store.targets()]


@router.post("/import", response_model=Target, status_code=201, dependencies=[Depends(require_token)],
             summary="A target from a file GET /targets/{name}/export wrote (this or another gateway's)",
             description="`file` is the bytes of a target's TIFF; what they hold is checked beyond this schema: "
                         "nothing is 422 `empty`, anything but a target file 422 `bad_target_file`.")
async def import_target(request: Request, core: Core,
                        file: Annotated[UploadFile | str | None, File(description="the target's TIFF (a file GET "
                                                                               "/targets/{name}/export wrote)")] = None,
                        name: Annotated[str | None, Form(max_length=80, description="store it under this name "
                                                                                     "instead")] = None,
                        replace: Annotated[bool, Form()] = False) -> Target:
    data = await read_upload(request, file if file is not None else "", "file")
    return Target.model_validate(core.import_target(data, name=name, replace=replace))


@router.get("/{name}", response_model=Target, summary="One stored target")
def target(name: str, core: Core) -> Target:
    return Target.model_validate(core.target(name))


@router.delete("/{name}", response_model=Target, dependencies=[Depends(require_token)],
               summary="Forget a stored target")
def delete(name: str, core: Core) -> Target:
    return Target.model_validate(core.delete_target(name))


@router.get("/{name}/thumbnail.png", response_class=Response,
            responses={200: {"content": {"image/png": {}}, "description": "a PNG image"}},
            summary="The stored reference, as a picture")
def thumbnail(name: str, core: Core) -> Response:
    return Response(to_png(core.target_pixels(name)), media_type="image/png")


@router.get("/{name}/export", response_class=Response,
            responses={200: {"content": {"image/tiff": {}}, "description": "the target as one TIFF"}},
            summary="The target as one file: a TIFF of its reference, the rest as JSON in its description")
def export(name: str, core: Core) -> Response:
    return Response(core.export_target(name), media_type="image/tiff",
                    headers={"Content-Disposition": f'attachment; filename="{name}.semservo-target.tif"'})


@router.post("/{name}/go", response_model=StartResult, dependencies=[Depends(require_token)],
             summary="Go back to a stored target: the stage to its stored pose (open loop), its reference taught, "
                     "then a positioning run on the image")
def go(name: str, core: Core, body: GoToTarget | None = None,
       resume: Annotated[bool, Query(description="let a stopped stage move again")] = False) -> StartResult:
    body = body or GoToTarget()
    started = core.go_to_target(name, body.settings.model_dump(), approach=body.approach, resume=resume)
    return StartResult(run_id=started["run_id"], state=started["state"])
