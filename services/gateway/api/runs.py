"""Positioning runs: start, stop, status, the records."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query
from fastapi.responses import Response

from semservo.api import RunRecord, RunSettings, RunSummary, StartResult, Status, StopRequest, StopResult
from semservo.errors import CommandError
from services.gateway.api.deps import Core, require_token
from services.gateway.core import reference_view
from services.gateway.report import report_png

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


@router.post("/stop", response_model=StopResult, dependencies=[Depends(require_token)],
             summary="Stop at once, any time: the stage first, then the run")
def stop(core: Core, body: StopRequest | None = None) -> StopResult:
    return StopResult.model_validate(core.stop((body or StopRequest()).reason))


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
    return Response(report_png(run_or_404(core, run_id)), media_type="image/png")


@router.get("/runs/{run_id}", response_model=RunRecord, summary="A run's full record")
def run(run_id: str, core: Core) -> RunRecord:
    return summary_of(run_or_404(core, run_id), RunRecord)
