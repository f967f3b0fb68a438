"""The REST API's application: the routers of :mod:`services.gateway.api`, one error
envelope, the token, the offline docs and the dashboard's files.

Error body, always: ``{"error": {"code": ..., "message": ..., "field": ...}}``; the status
comes from the code (:func:`semservo.errors.http_status`).
"""

from __future__ import annotations

import asyncio
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse

from semservo import __version__
from semservo.api import ErrorResponse
from services.gateway.api import docs, errors, images, live, runs, stage, targets, teach
from services.gateway.core import GatewayCore


def create_app(core: GatewayCore, *, api_token: str | None = None, max_upload_bytes: int = 32 * 2**20,
               static_dir: Path | None = None) -> FastAPI:
    listeners = live.Listeners()

    @asynccontextmanager
    async def lifespan(_app: FastAPI):
        listeners.loop = asyncio.get_running_loop()  # where WebSocket messages are delivered from threads
        listeners.closing = asyncio.Event()
        yield
        listeners.loop = None

    app = FastAPI(
        lifespan=lifespan, title="semservo", version=__version__, docs_url=None, redoc_url=None,
        summary="Image-guided nanopositioning for SEM (Marturi et al.): teach, jog, position, watch, records.",
        responses={code: {"model": ErrorResponse} for code in (400, 401, 404, 409, 413, 415, 422, 503)},
    )
    app.state.core = core
    app.state.api_token = api_token
    app.state.max_upload_bytes = max_upload_bytes
    app.state.listeners = listeners
    app.state.publish = listeners.publish
    errors.install(app)
    for router in (teach.router, stage.router, runs.router, targets.router, images.router, live.router):
        app.include_router(router)
    docs.install(app)
    if api_token is None:
        # The OpenAPI says what is true: bearer security only where a token is required.
        _drop_security(app)
    if static_dir is not None:
        from fastapi.staticfiles import StaticFiles

        # The page at /, its files under /dashboard/: a catch-all mount at / would answer
        # for the API's paths too (a 405 listing GET for a POST endpoint).
        @app.get("/", include_in_schema=False)
        def dashboard() -> FileResponse:
            return FileResponse(static_dir / "index.html", headers={"Cache-Control": "no-cache"})

        app.mount("/dashboard", StaticFiles(directory=static_dir), name="dashboard")
    return app


def _drop_security(app: FastAPI) -> None:
    """A loopback gateway without a token asks for none: its schema declares none."""
    original = app.openapi

    def openapi() -> dict:
        if app.openapi_schema is None:
            schema = original()
            for path in schema.get("paths", {}).values():
                for operation in path.values():
                    if isinstance(operation, dict):
                        operation.pop("security", None)
            schema.get("components", {}).pop("securitySchemes", None)
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi
