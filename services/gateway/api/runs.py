"""Positioning runs: start, stop, status, the records."""

from __future__ import annotations

import asyncio
import json
from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import Response
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect

from semservo.api import RunRecord, RunSettings, RunSummary, StartResult, Status, StopRequest, StopResult
from semservo.errors import CommandError
from semservo.protocol import carryable_text
from services.gateway.api.deps import Core, require_token
from services.gateway.core import reference_view

router = APIRouter(tags=["runs"])

PNG = {200: {"content": {"image/png": {}}, "description": "a PNG image"}}


def summary_of(run: dict, model=RunSummary):
    return model.model_validate({key: run[key] for key in model.model_fields if key in run})


@router.post("/start", response_model=StartResult, dependencies=[Depends(require_token)],
             summary="Start a positioning run (409 with the active run's id if one is running; 409 stage_stopped if "
                     "an operator stopped the stage, unless resume=true; 422 naming a DOF the instrument cannot "
                     "measure)")
def start(core: Core, settings: RunSettings | None = None,
          resume: Annotated[bool, Query(description="let a stopped stage move again (the operator's word, as POST "
                                                    "/stage/resume)")] = False) -> StartResult:
    started = core.start((settings or RunSettings()).model_dump(), resume=resume)
    return StartResult(run_id=started["run_id"], state=started["state"])


#: A stop's reason is kept to this many characters (a longer one is cut, not refused).
STOP_REASON_CHARS = StopRequest.model_fields["reason"].metadata[0].max_length
#: The most of a stop's body read; beyond it the body is not used (the stop is made).
STOP_BODY_BYTES = 16_384
#: The longest a stop waits for its body to arrive (then it stops with the default reason).
STOP_BODY_WAIT_S = 1.0


def stop_reason(body: bytes) -> tuple[str, str | None]:
    """The reason a stop's body gives, and why the body was not used, if it was not. A
    stop is never refused for its body: a reason of the wrong type, a misspelt field, a
    body that is not JSON still stop the stage (a 422 there once left a run going)."""
    default = StopRequest().reason
    if not body.strip():
        return default, None
    try:
        fields = json.loads(body)
    except (ValueError, RecursionError):  # RecursionError: nested deeper than the parser goes
        return default, "the body is not JSON the gateway can read"
    if fields is None:
        return default, None
    if not isinstance(fields, dict):
        return default, "the body is not a JSON object"
    unknown = sorted(set(fields) - {"reason"})
    reason = fields.get("reason", default)
    if reason is None:
        reason = default
    if not isinstance(reason, str):
        return default, f"reason is not a string ({type(reason).__name__})"
    reason, changed = carryable_text(reason, STOP_REASON_CHARS)
    said = ([f"unknown fields ignored: {', '.join(unknown)[:100]}"] if unknown else []) + \
        [f"reason: {change}" for change in changed]
    return reason or default, "; ".join(said) or None


async def _stop_body(request: Request) -> bytes | None:
    """The stop's body, or None once it is over :data:`STOP_BODY_BYTES` (a stop waits for
    no more body than a reason needs)."""
    body = b""
    async for chunk in request.stream():
        body += chunk
        if len(body) > STOP_BODY_BYTES:
            return None
    return body


@router.post("/stop", response_model=StopResult, dependencies=[Depends(require_token)],
             summary="Stop at once, any time: the stage first, then the run. Never refused for its body: a body "
                     "that cannot be read stops all the same (body_ignored says why)",
             openapi_extra={"requestBody": {"required": False, "content": {
                 "application/json": {"schema": StopRequest.model_json_schema()}}}})
async def stop(core: Core, request: Request) -> StopResult:
    try:
        body = await asyncio.wait_for(_stop_body(request), STOP_BODY_WAIT_S)
        reason, problem = (StopRequest().reason, f"the body is over {STOP_BODY_BYTES} bytes") if body is None \
            else stop_reason(body)
    except (asyncio.TimeoutError, ClientDisconnect):  # stop now; the body was too slow or was cut off
        reason, problem = StopRequest().reason, "the body did not arrive whole and in time"
    except Exception as error:  # noqa: BLE001 - whatever the body did, the stop is made
        reason, problem = StopRequest().reason, f"the body could not be read ({type(error).__name__})"
    stopped = await run_in_threadpool(core.stop, reason)
    return StopResult.model_validate({**stopped, "body_ignored": problem})


@router.get("/status", response_model=Status, summary="State, errors, latencies, the reference, every service's "
                                                      "health")
def status(core: Core) -> Status:
    state = core.status()
    return Status.model_validate({**state, "reference": reference_view(state["reference"])})


@router.get("/runs", response_model=list[RunSummary], summary="Run history, newest first")
def runs(core: Core, limit: Annotated[int, Query(ge=1, le=1000)] = 100,
         offset: Annotated[int, Query(ge=0, le=1_000_000_000)] = 0) -> list[RunSummary]:
    return [summary_of(run) for run in core.store.list_runs(limit, offset)]


def run_or_404(core, run_id: str) -> dict:
    run = core.store.get_run(run_id)
    if run is None:
        raise CommandError("no_such_run", f"no run {run_id!r}", field="run_id")
    return run


@router.get("/runs/{run_id}.csv", response_class=Response, summary="A run's iterations as CSV",
            responses={200: {"content": {"text/csv": {}}, "description": "one row per iteration"}})
def run_csv(run_id: str, core: Core) -> Response:
    run_or_404(core, run_id)
    return Response(core.store.csv(run_id), media_type="text/csv",
                    headers={"Content-Disposition": f'attachment; filename="{run_id}.csv"'})


@router.get("/runs/{run_id}/report.png", response_class=Response, responses=PNG,
            summary="Error, cost and voltages per iteration (Fig. 9)")
def run_report(run_id: str, core: Core) -> Response:
    return Response(core.run_report(run_or_404(core, run_id)), media_type="image/png")


@router.get("/runs/{run_id}", response_model=RunRecord, summary="A run's full record")
def run(run_id: str, core: Core) -> RunRecord:
    return summary_of(run_or_404(core, run_id), RunRecord)
