"""The controller's commands (``services/controller``): start a positioning run, stop it,
ask how it goes, read a run's record. :class:`RunSettings` is also the body of the
gateway's ``POST /start``.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, Field, PositiveFloat, PositiveInt, field_validator, model_validator

from semservo.protocol import CommandReply, CommandRequest, CommandSet, NoArguments

COMMANDS = CommandSet("controller", "Turns motion into stage moves, one run at a time (paper eq. 30-37): the run "
                                    "state machine, the control law, the run records. REP `:5580`; events on PUB "
                                    "`:5581`.")


def _whole(value):
    """A JSON number with no fraction (297.0) is a whole number, as JSON Schema says; 297.5,
    text and booleans stay refused (the model is strict)."""
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return value


#: A count: a positive whole number, given as 3 or 3.0.
Count = Annotated[PositiveInt, BeforeValidator(_whole)]

#: Degrees of freedom a run may servo ("gamma" is another name of "rotation").
Dof = Literal["x", "y", "rotation", "gamma", "alpha", "beta"]


class RunSettings(BaseModel):
    """What a positioning run may be told; every field has a sane default."""

    model_config = {"extra": "forbid", "allow_inf_nan": False, "strict": True}

    dofs: list[Dof] = Field(
        ["x", "y"], min_length=1, max_length=5, json_schema_extra={"uniqueItems": True},
        description="degrees of freedom, each once: x, y, rotation (about the beam; also called gamma: both names "
                    "together are one degree of freedom), alpha and beta (the tilts about the image's x and y axes, "
                    "measured from focus sweeps)")

    @field_validator("dofs")
    @classmethod
    def _each_once(cls, dofs: list[str]) -> list[str]:
        # The schema says uniqueItems, so a repeated name is a malformed body (422) at the
        # gateway, not a request the controller refuses after it was accepted.
        if len(set(dofs)) != len(dofs):
            raise ValueError(f"each degree of freedom once, got {dofs}")
        return dofs
    tolerance_px: PositiveFloat = Field(0.1, le=50, description="converged when the translation error is below")
    tolerance_deg: PositiveFloat = Field(0.05, le=10, description="and the rotation error below (rotation DOF)")
    tolerance_tilt_deg: PositiveFloat = Field(0.1, le=10, description="and each tilt error below (alpha, beta DOFs)")
    max_turn_deg: PositiveFloat = Field(5.0, le=30, description="largest turn or tilt per iteration (saturation)")
    min_tilt_confidence: float = Field(0.3, ge=0, le=1, description="less confident tilt measurements hold the tilts")
    converge_frames: Count = Field(3, le=100, description="the paper's law: converged when the mean error size (each frame's, errors either side do not cancel) of this many fresh frames "
                                                          "is under tolerance (the position law converges on its own estimate)")
    converge_on: Literal["mean", "each"] = Field(
        "mean", description="the paper's law: 'mean': their mean error is under tolerance; 'each': every one of them is too "
                            "(lands nearer, takes more frames, and may never end where vibration exceeds the tolerance)")
    max_iterations: Count = Field(150, le=100_000, description="moves before the run fails")
    law: Literal["position", "paper"] = Field(
        "position", description="the law: 'position' (the default), a position-based step that commands the whole "
                                "measured displacement through the stage's model, learns the stage's gain and the "
                                "drift (a Kalman filter) and converges on its own estimate, in 4-6 fresh frames where "
                                "the paper's law takes 18-50 (semservo.control.PositionLaw; it ignores gain and "
                                "integral_time_s), and undoes the tilts the focus sweeps measure in one move "
                                "(PositionTiltLaw); 'paper', the paper's velocity law (eq. 30-37, with gain and "
                                "integral_time_s) for x, y, rotation and the tilts")
    gain: Literal["adaptive", "exponential"] = Field("adaptive", description="eq. 35, or the exponential gain")
    gain_scale: PositiveFloat = Field(50.0, le=1e6, description="Lambda of eq. 35 (error x s)")
    gain_min: PositiveFloat = Field(0.5, le=10, description="per second; at most gain_max (else refused, 422)")
    gain_max: PositiveFloat = Field(0.8, le=10, description="per second; at least gain_min")
    min_confidence: float = Field(0.5, ge=0, le=1, description="lower-confidence estimates hold the stage")
    lost_after: Count = Field(10, le=1000, description="low-confidence frames in a row: the scene is lost")
    tilts_lost_after: Count = Field(3, le=100, description="fresh focus sweeps in a row that cannot tell the tilts "
                                                           "(alpha, beta DOFs): the tilts are lost, the run fails "
                                                           "with the last sweep's reason")
    max_move_um: PositiveFloat = Field(10.0, le=100, description="largest stage move per command (saturation)")
    moves_per_frame: Count = Field(
        3, le=10, description="the position law: once a move of the run has moved the content as commanded, a "
                              "displacement beyond max_move_um is made on one frame as up to this many commands of "
                              "at most max_move_um each, each written once the last has settled (1: one per frame; "
                              "the paper's law makes one)")
    partial_frames: bool | None = Field(
        None, description="act on a partial frame: the rows of the scan a move lands in that were scanned after it "
                          "settled (at least half of them), a scan sooner than the next whole frame (null: the law's "
                          "default, on for the position law, off for the paper's, whose velocity law is no faster "
                          "for more frequent frames). Needs a source that times its scans (the simulated SEM, a "
                          "scan generator's adapter); others give whole frames")
    beam_shift_within_um: float = Field(
        0.0, ge=0, le=1000, description="once the error is at most this many um, the beam shift (beam_x, beam_y) makes "
                                        "the moves while it has room, the stage the rest: the beam makes the last "
                                        "micrometres and holds against drift (0: the stage makes every move)")
    integral_time_s: float | None = Field(
        10.0, gt=0, le=1000,
        description="integral action T_i in seconds, against drift (null: the paper's proportional law)")
    hold: bool = Field(False, description="keep servoing after convergence (hold against drift)")
    diverge_factor: float = Field(4.0, gt=1, le=1e6, description="cost above this x its minimum ...")
    diverge_iterations: Count = Field(5, le=1000, description="... for this many moves in a row: diverging")
    diverge_floor_px: PositiveFloat = Field(
        1.0, le=100, description="... never judged on errors under this (estimation noise and vibration near the "
                                 "target are not divergence, however small the tolerance)")
    stall_after: Count = Field(
        60, le=100_000, description="no progress: this many fresh estimates outside tolerance without the error "
                                    "falling to 0.9 x its best so far (for the tilts: at least 4 focus sweeps) and the "
                                    "run fails, saying so")
    estimate_timeout_s: PositiveFloat = Field(
        5.0, le=600, description="no estimate against the run's reference for this long (wall clock): the run fails")

    @model_validator(mode="after")
    def _gains_in_order(self) -> "RunSettings":
        # eq. 35 clips the gain to [gain_min, gain_max]: the other way round, the minimum
        # asked for would be ignored without a word.
        if self.gain_min > self.gain_max:
            raise ValueError(f"gain_min ({self.gain_min:g}) is above gain_max ({self.gain_max:g})")
        return self


ControllerState = Literal["idle", "servoing", "converged", "failed", "stopped"]


class ControllerStatus(CommandReply):
    """The controller's state and the active (or last) run's progress."""

    state: ControllerState
    reason: str = ""
    run_id: str | None = None
    dofs: list[str] = Field(default_factory=list, description="the run's degrees of freedom (gamma as rotation)")
    started_at_ns: int | None = None
    iteration: int = Field(0, description="moves made")
    error_px: float | None = Field(None, description="the last fresh frame's translation error (the whole view's, "
                                                     "servoed or not)")
    mean_error_px: float | None = Field(None, description="the translation error convergence is judged on, along the "
                                                          "planar axes the run servoes: the position law's estimate, or "
                                                          "the paper's law's mean over the last converge_frames fresh "
                                                          "frames; null for a run that servoes neither x nor y")
    error_um: float | None = None
    cost: float | None = None
    rotation_deg: float | None = Field(None, description="the last rotation error about the beam (gamma)")
    alpha_deg: float | None = Field(None, description="the last measured tilt error about x")
    beta_deg: float | None = Field(None, description="the last measured tilt error about y")
    tilt_iterations: int = 0
    last_latency_ms: float | None = None
    held_stale: int = 0
    fresh_frames: int = Field(0, description="fresh, confident estimates the run has used")
    time_to_target_s: float | None = Field(None, description="a converged run: wall seconds from start to "
                                                             "convergence")
    path: str | None = Field(None, description="where the run's record is written")


class StopRequest(CommandRequest):
    reason: str = Field("stop requested", max_length=500)


class RunRequest(CommandRequest):
    id: str | None = Field(None, max_length=64, description="a run id; none: the active or last run")


class RunRecord(CommandReply):
    """A run's whole record (also ``runs/<id>.json``)."""

    model_config = {"extra": "allow"}

    id: str | None = None
    reference_id: str | None = None
    settings: dict[str, Any] | None = None
    started_at_ns: int | None = None
    stage_at_start: dict[str, Any] | None = None
    iterations: int = 0
    records: list[dict[str, Any]] = Field(default_factory=list, description="every iteration, in order")
    outcome: dict[str, Any] | None = Field(None, description="state, reason, finished_at_ns, iterations, and "
                                                             "fresh_frames, time_to_target_s when converged")
    stage_log: list[dict[str, Any]] = Field(default_factory=list, description="the stage's serial command log")
    min_cost: float | None = None
    held_stale: int = 0
    path: str | None = None


START = COMMANDS.add("start", RunSettings, ControllerStatus,
                     "start a run towards the estimator's current reference (`busy` while one runs, `no_reference` "
                     "before a teach, a DOF the instrument cannot measure refused with the reason)", timeout_s=15.0)
STOP = COMMANDS.add("stop", StopRequest, ControllerStatus, "stop at once: the stage first, then the run")
STATUS = COMMANDS.add("status", NoArguments, ControllerStatus, "state and the active or last run's progress")
RUN = COMMANDS.add("run", RunRequest, RunRecord, "the active or last run's record, or a finished one's by id "
                                                 "(`no_such_run`)", timeout_s=5.0)

