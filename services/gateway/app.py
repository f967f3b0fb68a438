"""The REST API (FastAPI): typed requests and responses, errors as 4xx bodies that name
the field and the reason, a bearer token on every state-changing endpoint when one is
configured. The work is done by :class:`services.gateway.core.GatewayCore`.

Error body, always: ``{"error": {"code": ..., "message": ..., "field": ...}}``.
"""


import asyncio
import hmac
import json
import logging
from contextlib import asynccontextmanager
from typing import Annotated, Any

from fastapi import Depends, FastAPI, File, Form, Query, Request, UploadFile, WebSocket, WebSocketDisconnect
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, PlainTextResponse, Response
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.exceptions import HTTPException as StarletteHTTPException
from pydantic import BaseModel, Field

from services.controller.core import RunSettings
from services.gateway.core import GatewayCore, GatewayError
from services.gateway.metrics import metrics_text
from services.gateway.report import report_png

log = logging.getLogger("gateway.api")


# -- models ------------------------------------------------------------------------
class ErrorBody(BaseModel):
    code: str
    message: str
    field: str | None = None


class ErrorResponse(BaseModel):
    error: ErrorBody


#: Every request model: unknown fields are an error, and so are NaN, infinity and a
#: value of another JSON type (``false`` is not the number 0).
STRICT = {"extra": "forbid", "allow_inf_nan": False, "strict": True}


class PolygonTeach(BaseModel):
    """Teach from a mask given by its corner points on the live image (paper case 6)."""

    model_config = STRICT
    polygon: list[Annotated[list[float], Field(min_length=2, max_length=2)]] = Field(
        min_length=3, max_length=1000, description="[[x, y], ...] in pixels")


class TeachResult(BaseModel):
    id: str
    kind: str
    shape: list[int]
    pixel_size_nm: float | None
    thumbnail_url: str
    acquisition: dict[str, Any] = Field(default_factory=dict, description=(
        "what the reference's source says of its acquisition: pixel_size_nm, magnification, dwell_ns, "
        "working_distance_mm, high_voltage_kv, detector, instrument, data_bar_rows (absent: not known)"))
    detail: dict[str, Any] = Field(default_factory=dict)
    tilt: dict[str, Any] | None = Field(None, description=(
        "taught with tilts: the taught pose's focus sweep (alpha_deg, beta_deg of its plane, centre_um, "
        "kernels_used, frames)"))


class MoveRequest(BaseModel):
    """A jog (relative) or a move to a target (absolute), on x, y or both."""

    # The schema says what the endpoint checks: at least one axis must be given.
    model_config = {**STRICT, "json_schema_extra": {"anyOf": [
        {"required": [axis], "properties": {axis: {"type": "number"}}} for axis in ("x_um", "y_um")]}}
    x_um: float | None = Field(None, ge=-100, le=100, description="micrometres (target, or step if relative)")
    y_um: float | None = Field(None, ge=-100, le=100)
    relative: bool = Field(True, description="a step from here (jog), or an absolute target")


class RotateRequest(BaseModel):
    """A turn about the beam and/or a tilt of the rotation-and-tilt stage, in degrees."""

    model_config = {**STRICT, "json_schema_extra": {"anyOf": [
        {"required": [axis], "properties": {axis: {"type": "number"}}}
        for axis in ("rotation_deg", "tilt_x_deg", "tilt_y_deg")]}}
    rotation_deg: float | None = Field(None, ge=-360, le=360, description="about the beam, counter-clockwise "
                                                                         "as displayed (target, or step if relative)")
    tilt_x_deg: float | None = Field(None, ge=-45, le=45, description="about the x axis")
    tilt_y_deg: float | None = Field(None, ge=-45, le=45, description="about the y axis")
    relative: bool = Field(True, description="a step from here, or an absolute target")


class CenterRequest(BaseModel):
    """A point of the live image (pixels, x right, y down) to bring to the centre."""

    model_config = STRICT
    x_px: float = Field(ge=0, le=100_000, description="column, from the left edge (must lie inside the current image)")
    y_px: float = Field(ge=0, le=100_000, description="row, from the top edge")


class StartResult(BaseModel):
    run_id: str
    state: str


class StopRequest(BaseModel):
    model_config = STRICT
    reason: str = Field("stop requested", max_length=200)


class ServiceHealth(BaseModel):
    up: bool
    state: str
    last_error: str | None = None


class Status(BaseModel):
    state: str
    reason: str = ""
    run_id: str | None
    iteration: int
    error_px: float | None
    error_um: float | None
    mean_error_px: float | None = None
    cost: float | None
    rotation_deg: float | None = Field(None, description="the last rotation error about the beam (gamma), degrees")
    alpha_deg: float | None = Field(None, description="the last measured tilt error about the image's x axis, degrees")
    beta_deg: float | None = Field(None, description="the last measured tilt error about the image's y axis, degrees")
    tilt: dict | None = Field(None, description="the estimator's last focus sweep: frames, kernels, a small depth "
                                                "map (um from the centre's focus; null where unclear)")
    last_latency_ms: float | None
    latency_p50_ms: float | None
    latency_p99_ms: float | None
    estimation_ms: float | None
    snr_db: float | None = None
    frame_rate: float
    latest_frame_seq: int | None
    frame_acquisition: dict[str, Any] = Field(default_factory=dict, description=(
        "the live frame's acquisition as its source knows it (pixel_size_nm, magnification, dwell_ns, "
        "working_distance_mm, high_voltage_kv, detector, instrument, data_bar_rows); absent: not known"))
    reference: dict | None
    stage: dict
    services: dict[str, ServiceHealth]
    down: list[str]
    degraded: list[str] = Field(default_factory=list, description="up, but not doing their job (e.g. a frozen "
                                                                   "frame source); last_error says why")


class RunSummary(BaseModel):
    id: str
    reference_id: str | None
    started_at_ns: int
    finished_at_ns: int | None
    state: str
    reason: str
    iterations: int
    final_error_px: float | None
    truth: dict | None


def error_response(status: int, code: str, message: str, field: str | None = None, **extra) -> JSONResponse:
    return JSONResponse({"error": {"code": code, "message": message, "field": field, **extra}}, status_code=status)


def create_app(core: GatewayCore, *, api_token: str | None = None, max_upload_bytes: int = 32 * 2**20,
               static_dir=None) -> FastAPI:
    @asynccontextmanager
    async def lifespan(app: FastAPI):
        app.state.loop = asyncio.get_running_loop()  # where WebSocket messages are delivered from threads
        yield
        app.state.loop = None

    app = FastAPI(
        lifespan=lifespan,
        title="semservo",
        summary="Image-guided nanopositioning for SEM (Marturi et al.): teach, jog, position, watch, records.",
        version="0.1.0",
        responses={code: {"model": ErrorResponse} for code in (400, 401, 404, 409, 413, 415, 422, 503)},
    )
    app.state.core = core
    app.state.listeners = set()
    bearer = HTTPBearer(auto_error=False)

    def authorized(credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]) -> None:
        if api_token is None:
            return
        given = credentials.credentials if credentials is not None else ""
        # Constant time, so the comparison leaks nothing of the token.
        if not hmac.compare_digest(given.encode(), api_token.encode()):
            raise GatewayError(401, "unauthorized", "a valid bearer token is required for this endpoint")

    # The OpenAPI says what is true: bearer security on state-changing endpoints when a
    # token is configured, none on a loopback gateway without one.
    Auth = [Depends(authorized)] if api_token is not None else []

    @app.exception_handler(GatewayError)
    async def gateway_error(_request: Request, error: GatewayError) -> JSONResponse:
        return error_response(error.status, error.code, error.message, **error.extra)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(_request: Request, error: StarletteHTTPException) -> JSONResponse:
        # The framework's own refusals (a body that does not parse, an unknown path, a
        # method a path does not take) in the same envelope as every other error.
        codes = {400: "bad_body", 404: "not_found", 405: "method_not_allowed"}
        response = error_response(error.status_code, codes.get(error.status_code, "http_error"), str(error.detail))
        for name, value in (error.headers or {}).items():
            response.headers[name] = value
        return response

    @app.exception_handler(RequestValidationError)
    async def validation_error(_request: Request, error: RequestValidationError) -> JSONResponse:
        first = error.errors()[0]
        location = [str(part) for part in first.get("loc", ()) if part not in ("body", "query", "path")]
        return error_response(422, "invalid", first.get("msg", "invalid request"), ".".join(location) or None)

    # -- teach ----------------------------------------------------------------------
    def taught(result: dict) -> TeachResult:
        detail = {k: v for k, v in result.items() if k not in ("id", "kind", "shape", "pixel_size_nm", "acquisition")}
        return TeachResult(id=result["id"], kind=result["kind"], shape=result["shape"],
                           pixel_size_nm=result.get("pixel_size_nm"), thumbnail_url="/reference.png",
                           acquisition=result.get("acquisition", {}), detail=detail, tilt=result.get("tilt"))

    async def read_upload(upload: UploadFile, field: str) -> bytes:
        data = await upload.read(max_upload_bytes + 1)
        if len(data) > max_upload_bytes:
            raise GatewayError(413, "too_large", f"{field}: uploads are limited to {max_upload_bytes} bytes", field=field)
        if not data:
            raise GatewayError(422, "empty", f"{field}: the upload is empty", field=field)
        return data

    @app.post("/teach", response_model=TeachResult, dependencies=Auth, tags=["teach"],
              summary="Teach the reference: the live frame(s), an uploaded image, or a mask")
    async def teach(
        request: Request,
        frames: Annotated[int, Query(ge=1, le=16, description="average this many live frames")] = 1,
        dwell_ns: Annotated[float | None, Query(gt=0, le=100_000, description="scan the reference once at this "
                                                "dwell (ns/px): a slow, high-quality reference")] = None,
        image: Annotated[UploadFile | None, File(description="PNG/TIFF reference of the current scan's size")] = None,
        mask: Annotated[UploadFile | None, File(description="PNG/TIFF binary mask (paper case 6)")] = None,
        label: Annotated[str | None, Form(max_length=200)] = None,
        tilts: Annotated[bool, Query(description="also sweep the focus at the taught pose, so a run can servo the "
                                                 "tilts alpha and beta (takes a sweep's scans: seconds)")] = False,
    ) -> TeachResult:
        if request.headers.get("content-type", "").split(";")[0].strip() == "application/json":
            # Said, not ignored: a script posting {"frames": 4} would otherwise get one frame.
            raise GatewayError(415, "json_body", "POST /teach takes query parameters (?frames=4, ?dwell_ns=...) "
                                                 "or a multipart upload (image or mask), not a JSON body")
        if sum(given is not None for given in (image, mask, dwell_ns)) > 1:
            raise GatewayError(422, "invalid", "give one of image, mask, dwell_ns", field="image")
        image_bytes = await read_upload(image, "image") if image is not None else None
        mask_bytes = await read_upload(mask, "mask") if mask is not None else None
        if tilts and (image is not None or mask is not None):
            raise GatewayError(422, "invalid", "tilts are taught from the live scan (a focus sweep), not with an "
                                               "uploaded image or mask", field="tilts")
        result = await asyncio.to_thread(core.teach, frames=frames, image=image_bytes, mask=mask_bytes, label=label,
                                         dwell_ns=dwell_ns, tilts=tilts)
        return taught(result)

    @app.post("/teach/polygon", response_model=TeachResult, dependencies=Auth, tags=["teach"],
              summary="Teach a mask drawn by corner points on the live image")
    def teach_polygon(body: PolygonTeach) -> TeachResult:
        return taught(core.teach(polygon=[list(point) for point in body.polygon]))

    # -- stage ----------------------------------------------------------------------
    @app.post("/stage/move", dependencies=Auth, tags=["stage"], summary="Jog (relative) or move (absolute), um")
    def move(body: MoveRequest) -> dict:
        targets = {axis: value for axis, value in (("x", body.x_um), ("y", body.y_um)) if value is not None}
        if not targets:
            raise GatewayError(422, "invalid", "give x_um and/or y_um", field="x_um")
        return core.move(targets, body.relative)

    @app.post("/stage/rotate", dependencies=Auth, tags=["stage"],
              summary="Turn or tilt the rotation-and-tilt stage, degrees (through the stage service's rules)")
    def rotate(body: RotateRequest) -> dict:
        targets = {axis: value for axis in ("rotation_deg", "tilt_x_deg", "tilt_y_deg")
                   if (value := getattr(body, axis)) is not None}
        if not targets:
            raise GatewayError(422, "invalid", "give rotation_deg, tilt_x_deg and/or tilt_y_deg", field="rotation_deg")
        return core.rotate(targets, body.relative)

    @app.post("/stage/center", dependencies=Auth, tags=["stage"],
              summary="Click to move: bring this point of the live image to its centre")
    def center(body: CenterRequest) -> dict:
        return core.center(body.x_px, body.y_px)

    @app.post("/stage/resume", dependencies=Auth, tags=["stage"],
              summary="Let a stopped (or watchdog-held) stage move again")
    def resume() -> dict:
        return core.resume()

    @app.get("/stage", tags=["stage"], summary="Position, voltages, limits and serial link state")
    def stage() -> dict:
        return core.stage_state()

    # -- runs -----------------------------------------------------------------------
    @app.post("/start", response_model=StartResult, dependencies=Auth, tags=["runs"],
              summary="Start a positioning run (409 with the active run's id if one is running; 409 "
                      "stage_stopped if an operator stopped the stage, unless resume=true)")
    def start(settings: RunSettings | None = None,
              resume: Annotated[bool, Query(description="let a stopped stage move again (the operator's word, as "
                                                        "POST /stage/resume)")] = False) -> StartResult:
        started = core.start((settings or RunSettings()).model_dump(), resume=resume)
        return StartResult(run_id=started["run_id"], state=started["state"])

    @app.post("/stop", dependencies=Auth, tags=["runs"], summary="Stop at once, any time")
    def stop(body: StopRequest | None = None) -> dict:
        return core.stop((body or StopRequest()).reason)

    @app.get("/status", response_model=Status, tags=["runs"], summary="State, errors, latencies, health of every service")
    def status() -> Status:
        return Status.model_validate(core.status())

    @app.get("/runs", response_model=list[RunSummary], tags=["runs"], summary="Run history, newest first")
    def runs(limit: Annotated[int, Query(ge=1, le=1000)] = 100,
             offset: Annotated[int, Query(ge=0, le=1_000_000_000)] = 0) -> list[RunSummary]:
        return [RunSummary.model_validate(run) for run in core.store.list_runs(limit, offset)]

    def run_or_404(run_id: str) -> dict:
        run = core.store.get_run(run_id)
        if run is None:
            raise GatewayError(404, "no_such_run", f"no run {run_id!r}", field="run_id")
        return run

    @app.get("/runs/{run_id}.csv", tags=["runs"], response_class=Response, summary="A run's iterations as CSV",
             responses={200: {"content": {"text/csv": {}}, "description": "one row per iteration"}})
    def run_csv(run_id: str) -> Response:
        run_or_404(run_id)
        return Response(core.store.csv(run_id), media_type="text/csv",
                        headers={"Content-Disposition": f'attachment; filename="{run_id}.csv"'})

    png = {200: {"content": {"image/png": {}}, "description": "a PNG image"}}

    @app.get("/runs/{run_id}/report.png", tags=["runs"], response_class=Response, responses=png,
             summary="Error, cost and voltages per iteration (Fig. 9)")
    def run_report(run_id: str) -> Response:
        return Response(report_png(run_or_404(run_id)), media_type="image/png")

    @app.get("/runs/{run_id}", tags=["runs"], summary="A run's full record")
    def run(run_id: str) -> dict:
        return run_or_404(run_id)

    # -- images ---------------------------------------------------------------------
    no_store = {"Cache-Control": "no-store"}

    @app.get("/frames/latest.png", tags=["images"], response_class=Response, responses=png,
             summary="The newest frame")
    def latest_frame() -> Response:
        return Response(core.latest_png(), media_type="image/png", headers=no_store)

    @app.get("/reference.png", tags=["images"], response_class=Response, responses=png,
             summary="The taught reference")
    def reference() -> Response:
        return Response(core.reference_png(), media_type="image/png", headers=no_store)

    @app.get("/difference.png", tags=["images"], response_class=Response, responses=png,
             summary="I - I* (levelled), grey is zero")
    def difference() -> Response:
        return Response(core.difference_png(), media_type="image/png", headers=no_store)

    # -- live -----------------------------------------------------------------------
    @app.get("/metrics", tags=["live"], response_class=PlainTextResponse, summary="Prometheus text format")
    def metrics() -> Response:
        body, content_type = metrics_text(core)
        return Response(body, media_type=content_type)

    @app.websocket("/events")
    async def events(socket: WebSocket) -> None:
        """Status and per-iteration records as they happen (JSON text messages). With a
        token configured, it must come as ``?token=`` (browsers cannot set headers on a
        WebSocket) or as a bearer header."""
        if api_token is not None:
            header = socket.headers.get("authorization", "")
            given = socket.query_params.get("token") or (header[7:] if header.lower().startswith("bearer ") else "")
            if not hmac.compare_digest(given.encode(), api_token.encode()):
                await socket.close(code=1008, reason="a valid token is required (?token=...)")
                return
        await socket.accept()
        queue: asyncio.Queue = asyncio.Queue(maxsize=1000)
        app.state.listeners.add(queue)
        try:
            await socket.send_text(json.dumps({"kind": "hello", "run_id": None, "data": core.last_status}))
            while True:
                message = await queue.get()
                await socket.send_text(message)
        except WebSocketDisconnect:
            log.debug("an events listener went away")
        finally:
            app.state.listeners.discard(queue)

    def publish(message: dict) -> None:
        """From any thread: hand a message to every WebSocket listener (a slow one drops)."""
        loop = app.state.loop
        if loop is None:
            return
        text = json.dumps(message, default=str)

        def deliver() -> None:
            for queue in list(app.state.listeners):
                if queue.full():
                    continue
                queue.put_nowait(text)

        loop.call_soon_threadsafe(deliver)

    app.state.loop = None
    app.state.publish = publish

    if static_dir is not None:
        from fastapi.responses import FileResponse
        from fastapi.staticfiles import StaticFiles

        # The page at /, its files under /dashboard/: a catch-all mount at / would answer
        # for the API's paths too (a 405 listing GET for a POST endpoint).
        @app.get("/", include_in_schema=False)
        def dashboard() -> FileResponse:
            return FileResponse(static_dir / "index.html", headers={"Cache-Control": "no-cache"})

        app.mount("/dashboard", StaticFiles(directory=static_dir), name="dashboard")
    return app

