"""Teaching the reference: the live frame(s), a slow scan, an upload, a mask."""

from __future__ import annotations

import asyncio
from typing import Annotated

from fastapi import APIRouter, Depends, File, Form, Query, Request, UploadFile

from semservo.api import PolygonTeach, TeachResult
from semservo.errors import BadRequest, CommandError
from services.gateway.api.deps import Core, require_token
from services.gateway.core import reference_view

router = APIRouter(tags=["teach"])


async def read_upload(request: Request, upload: UploadFile | str, field: str) -> bytes:
    """An upload's bytes (a part sent without a file name, as text, is read the same way),
    refused when empty or over the size limit."""
    limit = request.app.state.max_upload_bytes
    data = upload.encode("utf-8", "surrogateescape")[:limit + 1] if isinstance(upload, str) \
        else await upload.read(limit + 1)
    if len(data) > limit:
        raise CommandError("too_large", f"{field}: uploads are limited to {limit} bytes", field=field)
    if not data:
        raise CommandError("empty", f"{field}: the upload is empty", field=field)
    return data


#: What POST /teach reads: its query parameters and its multipart form's parts.
TEACH_QUERY = frozenset({"frames", "dwell_ns", "tilts"})
TEACH_PARTS = frozenset({"image", "mask", "label"})
FORM_TYPES = frozenset({"multipart/form-data", "application/x-www-form-urlencoded"})


@router.post("/teach", response_model=TeachResult, dependencies=[Depends(require_token)],
             summary="Teach the reference: the live frame(s), one slow scan, an uploaded image, or a mask",
             description="An `image` or `mask` is the bytes of a PNG or TIFF file (8 or 16 bit) of the current "
                         "scan's size; a part sent as text is read the same way. What the bytes hold is checked "
                         "beyond this schema: not a readable PNG/TIFF is 422 `unreadable_image`, another size "
                         "422 `wrong_size`, nothing 422 `empty`, over the upload limit 413 `too_large`.")
async def teach(
    request: Request, core: Core,
    frames: Annotated[int, Query(ge=1, le=16, description="average this many live frames")] = 1,
    dwell_ns: Annotated[float | None, Query(gt=0, le=100_000, description="scan the reference once at this "
                                            "dwell (ns/px): a slow, high-quality reference")] = None,
    image: Annotated[UploadFile | str | None, File(description="PNG/TIFF reference of the current scan's size")] = None,
    mask: Annotated[UploadFile | str | None, File(description="PNG/TIFF binary mask (paper case 6)")] = None,
    label: Annotated[str | None, Form(max_length=200)] = None,
    tilts: Annotated[bool, Query(description="also sweep the focus at the taught pose, so a run can servo the tilts "
                                             "alpha and beta: the answer comes at once, the sweep goes on (seconds; "
                                             "`tilt_teach` in GET /reference says how far)")] = False,
) -> TeachResult:
    if request.headers.get("content-type", "").split(";")[0].strip() == "application/json":
        # Said, not ignored: a script posting {"frames": 4} would otherwise get one frame.
        raise CommandError("json_body", "POST /teach takes query parameters (?frames=4, ?dwell_ns=...) or a "
                                        "multipart upload (image or mask), not a JSON body")
    # A misspelt part or parameter (`imag=@file`, `?frame=4`) would otherwise teach the
    # live frame in place of what was meant: said, as a JSON body is.
    unknown = sorted(set(request.query_params) - TEACH_QUERY)
    if request.headers.get("content-type", "").split(";")[0].strip() in FORM_TYPES:
        unknown += sorted(set((await request.form()).keys()) - TEACH_PARTS)
    if unknown:
        raise BadRequest(f"POST /teach does not take {', '.join(map(repr, unknown))}: its parameters are "
                         f"{', '.join(sorted(TEACH_QUERY))} and its form parts {', '.join(sorted(TEACH_PARTS))}",
                         field=unknown[0])
    if sum(given is not None for given in (image, mask, dwell_ns)) > 1:
        raise BadRequest("give one of image, mask, dwell_ns", field="image")
    image_bytes = await read_upload(request, image, "image") if image is not None else None
    mask_bytes = await read_upload(request, mask, "mask") if mask is not None else None
    if tilts and (image is not None or mask is not None):
        raise BadRequest("tilts are taught from the live scan (a focus sweep), not with an uploaded image or mask",
                         field="tilts")
    result = await asyncio.to_thread(core.teach, frames=frames, image=image_bytes, mask=mask_bytes, label=label,
                                     dwell_ns=dwell_ns, tilts=tilts)
    return TeachResult.model_validate(reference_view(result))


@router.post("/teach/polygon", response_model=TeachResult, dependencies=[Depends(require_token)],
             summary="Teach a mask drawn by corner points on the live image",
             description="At least three distinct corner points, on or near the live image, enclosing 256 square "
                         "pixels or more (checked beyond this schema: a 422 naming the reason).")
def teach_polygon(body: PolygonTeach, core: Core) -> TeachResult:
    points = [tuple(point) for point in body.polygon]
    if len(set(points)) != len(points):
        raise BadRequest("polygon: each corner point once", field="polygon")
    return TeachResult.model_validate(reference_view(core.teach(polygon=[list(point) for point in body.polygon])))


@router.get("/reference", response_model=TeachResult, summary="The taught reference (whoever taught it), with its "
                                                              "focus sweep's progress after a teach with tilts")
def reference(core: Core) -> TeachResult:
    return TeachResult.model_validate(reference_view(core.current_reference()))
