"""The REST API's models: what the gateway (``services/gateway``) takes and answers, and
what :mod:`semservo.client` hands back to a lab script. One definition for both sides:
the OpenAPI schema, the gateway's responses and the client's return types cannot drift.

Every response model reads as attributes (``run.state``) and, for scripts written when
the client returned dictionaries, as items (``run["state"]``).

Error body, always: ``{"error": {"code": ..., "message": ..., "field": ...}}``.
"""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field

from semservo.protocol import CommandReply
from semservo.protocol.controller import ControllerStatus, RunSettings
from semservo.protocol.estimator import FocusMeasure
from semservo.protocol.stage import MoveReply, RotateReply, StageState

__all__ = ["CenterRequest", "ControllerStatus", "ErrorBody", "ErrorResponse", "MoveReply", "MoveRequest",
           "PolygonTeach", "RotateReply", "RotateRequest", "RunRecord", "RunSettings", "RunSummary", "ServiceHealth",
           "StageState", "StartResult", "Status", "StopRequest", "StopResult", "Target", "TargetRequest",
           "GoToTarget", "TeachResult"]

#: Every request model: unknown fields are an error, and so are NaN, infinity and a
#: value of another JSON type (``false`` is not the number 0).
STRICT = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)


class Response(CommandReply):
    """Base of every response: attributes and items both."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class ErrorBody(BaseModel):
    code: str
    message: str
    field: str | None = None


class ErrorResponse(BaseModel):
    error: ErrorBody


# -- teach -------------------------------------------------------------------------------
Point = Annotated[list[float], Field(min_length=2, max_length=2)]


class PolygonTeach(BaseModel):
    """Teach from a mask given by its corner points on the live image (paper case 6):
    at least three distinct points enclosing 256 square pixels or more."""

    model_config = STRICT
    polygon: list[Point] = Field(min_length=3, max_length=1000, json_schema_extra={"uniqueItems": True},
                                 description="[[x, y], ...] in pixels of the live image, each point once")


class TiltTeach(Response):
    """The taught pose's focus sweeps: they run after a teach with tilts (seconds each):
    one, or more of the same view pooled while they pin the tilts loosely."""

    state: str = Field(description="sweeping, done or failed")
    reference_id: str | None = None
    scanned: int = 0
    frames: int = 0
    sweep: int = Field(1, description="which sweep is scanning (or the last one), from 1")
    max_sweeps: int = Field(1, description="the most sweeps the teach takes before it refuses")
    fine: bool = Field(False, description="the wide sweeps could not pin the tilts: these sweep the view finely, a "
                                          "quarter of a depth of field apart, about the depths they found")
    wide_sweeps: int = Field(0, description="fine: how many wide sweeps came before the fine ones (sweep and "
                                            "max_sweeps count both)")
    focus_measure: FocusMeasure = Field(
        "normalized_variance", description="the focus measure the sweeps are read by "
                                           "(SEMSERVO_ESTIMATOR__TILT_FOCUS_MEASURE): eq. 13 or the gradient energy")
    pinned_deg: list[float] | None = Field(None, description="the standard errors of alpha and beta (degrees) from "
                                                             "the sweeps so far, pooled")
    error: str | None = None
    code: str | None = Field(None, description="failed: sweep_failed, or no_tilt_reference (the sweep cannot tell "
                                               "the tilts at these settings)")


class TeachResult(Response):
    """The taught reference: the estimator's, the one truth of it (the CLI's teach, a
    stored target's and the dashboard's are the same)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    id: str
    kind: str = Field(description="frame, image or mask")
    shape: list[int]
    pixel_size_nm: float | None
    thumbnail_url: str = "/reference.png"
    taught_at_ns: int | None = None
    acquisition: dict[str, Any] = Field(default_factory=dict, description=(
        "what the reference's source says of its acquisition: pixel_size_nm, magnification, dwell_ns, "
        "working_distance_mm, high_voltage_kv, detector, instrument, data_bar_rows (absent: not known)"))
    detail: dict[str, Any] = Field(default_factory=dict, description="frame_seq, frames_averaged, label, polygon ...")
    tilt: dict[str, Any] | None = Field(None, description=(
        "taught with tilts: the taught pose's focus sweep (alpha_deg, beta_deg of its plane, centre_um, "
        "kernels_used, frames)"))
    tilt_teach: TiltTeach | None = Field(None, description="taught with tilts: how far its focus sweep is")
    target: str | None = Field(None, description="the stored target it was taught from, if any")


# -- stage ---------------------------------------------------------------------------------
#: A move's sanity bound (um): beyond any stage semservo drives (10 mm). Below it the
#: stage's own soft limits decide, with the rule's name (a fixed +-100 refused a move a
#: long-travel stage's settings allowed, before the stage was asked).
MOVE_BOUND_UM = 10_000.0


class MoveRequest(BaseModel):
    """A jog (relative) or a move to a target (absolute), on x, y or both."""

    # The schema says what the endpoint checks: at least one axis must be given.
    model_config = {**STRICT, "json_schema_extra": {"anyOf": [
        {"required": [axis], "properties": {axis: {"type": "number"}}} for axis in ("x_um", "y_um")]}}
    x_um: float | None = Field(None, ge=-MOVE_BOUND_UM, le=MOVE_BOUND_UM,
                               description="micrometres (target, or step if relative); the stage's soft limits apply")
    y_um: float | None = Field(None, ge=-MOVE_BOUND_UM, le=MOVE_BOUND_UM)
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


# -- runs ----------------------------------------------------------------------------------
class StartResult(Response):
    run_id: str
    state: str


class StopRequest(BaseModel):
    model_config = STRICT
    reason: str = Field("stop requested", max_length=200)


class StopResult(ControllerStatus):
    """The controller's status after the stop, and whether the stage took it."""

    stage_stopped: bool = Field(description="the stage service took the stop (it refuses moves until resumed)")
    stage_error: str | None = None
    controller: str | None = Field(None, description="why the controller did not answer (the stage stopped all "
                                                     "the same)")
    body_ignored: str | None = Field(None, description="why the request's body was not used as it was (the stop "
                                                       "was made all the same)")


class ServiceHealth(Response):
    up: bool
    state: str
    last_error: str | None = None


class Status(Response):
    state: str
    reason: str = ""
    run_id: str | None
    dofs: list[str] = Field(default_factory=list, description="the run's degrees of freedom")
    iteration: int
    error_px: float | None
    error_um: float | None
    mean_error_px: float | None = None
    cost: float | None
    rotation_deg: float | None = Field(None, description="the last rotation error about the beam (gamma), degrees")
    alpha_deg: float | None = Field(None, description="the last measured tilt error about the image's x axis, degrees")
    beta_deg: float | None = Field(None, description="the last measured tilt error about the image's y axis, degrees")
    fresh_frames: int = Field(0, description="fresh frames the run has used")
    time_to_target_s: float | None = Field(None, description="a converged run: seconds from start to convergence")
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
    frame_shape: list[int] | None = Field(None, description="rows, columns of the live frame")
    reference: TeachResult | None
    stage: dict
    services: dict[str, ServiceHealth]
    down: list[str]
    degraded: list[str] = Field(default_factory=list, description="up, but not doing their job (e.g. a frozen "
                                                                   "frame source); last_error says why")


class RunSummary(Response):
    id: str
    reference_id: str | None
    started_at_ns: int
    finished_at_ns: int | None
    state: str
    reason: str
    iterations: int
    final_error_px: float | None = Field(description="the translation error the run judged last (px, along the planar "
                                                     "axes it servoes); null for a run that servoes neither x nor y")
    truth: dict | None
    dofs: list[str] = Field(default_factory=list)
    duration_s: float | None = Field(None, description="from start to end (or to now, for a run still servoing)")
    fresh_frames: int | None = None
    partial_frames: int | None = Field(None, description="of the fresh frames, those measured on the rows "
                                                         "scanned after a move (a partial frame)")
    time_to_target_s: float | None = Field(None, description="a converged run: wall seconds from start to "
                                                          "convergence")
    source_time_to_target_s: float | None = Field(
        None, description="the same on the image source's clock, from the first frame's scan to the last's (the "
                          "simulated lab's time: what the run takes at the microscope's frame rate, whatever its "
                          "speed-up); absent for a source without scan times")


class RunRecord(RunSummary):
    """A run's whole record: settings, every iteration, the stage's command log, the
    outcome and, on simulated hardware, the true final error."""

    settings: dict[str, Any] | None
    reference: dict[str, Any] | None
    outcome: dict[str, Any] | None
    trajectory: list[dict[str, Any]] = Field(description="every iteration, in order")
    stage_commands: list[dict[str, Any]] = Field(description="every line exchanged with the amplifier")


# -- stored targets ------------------------------------------------------------------------
class TargetRequest(BaseModel):
    """Store the taught reference under a name (with the stage's pose and the
    acquisition it was taught at), to come back to days later."""

    model_config = STRICT
    name: str = Field(min_length=1, max_length=80, pattern=r"^[A-Za-z0-9][A-Za-z0-9 ._-]*$",
                      description="letters, digits, space, '.', '_', '-'")
    note: str = Field("", max_length=2000, description="what it is, for the people who come back to it")
    replace: bool = Field(False, description="replace a target of the same name")


class Target(Response):
    name: str
    note: str = ""
    created_at_ns: int
    reference: dict[str, Any] = Field(description="the reference as it was taught (kind, shape, pixel size, "
                                                  "acquisition, tilt ...)")
    stage: dict[str, Any] = Field(description="where the stage was: positions_um, voltages, rotation angles")
    acquisition: dict[str, Any] = Field(default_factory=dict)
    thumbnail_url: str
    export_url: str


class GoToTarget(BaseModel):
    """Go back to a stored target: teach its reference, optionally bring the stage near
    its stored pose first (open loop), then position on the image (a run)."""

    model_config = STRICT
    approach: bool = Field(True, description="first move the stage to the stored positions (open loop, through the "
                                             "stage's model and every rule), then servo on the image")
    settings: RunSettings = Field(default_factory=RunSettings, description="the run's settings")
