"""The images the dashboard shows: the live frame, the reference, their difference."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import Response

from services.gateway.api.deps import Core

router = APIRouter(tags=["images"])

PNG = {200: {"content": {"image/png": {}}, "description": "a PNG image"}}
NO_STORE = {"Cache-Control": "no-store"}


@router.get("/frames/latest.png", response_class=Response, responses=PNG, summary="The newest frame")
def latest_frame(core: Core) -> Response:
    return Response(core.latest_png(), media_type="image/png", headers=NO_STORE)


@router.get("/reference.png", response_class=Response, responses=PNG, summary="The taught reference")
def reference(core: Core) -> Response:
    return Response(core.reference_png(), media_type="image/png", headers=NO_STORE)


@router.get("/difference.png", response_class=Response, responses=PNG, summary="I - I* (levelled), grey is zero")
def difference(core: Core) -> Response:
    return Response(core.difference_png(), media_type="image/png", headers=NO_STORE)
