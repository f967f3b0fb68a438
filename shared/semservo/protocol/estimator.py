"""The estimator's commands (``services/estimator``): the taught reference (the one truth
of it: the gateway, the dashboard and the CLI all read it from here), and what is
measured per frame.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import Field

from semservo.protocol import CommandReply, CommandRequest, CommandSet, NoArguments

COMMANDS = CommandSet("estimator", "Measures each frame's motion against the taught reference (paper section II) "
                                   "and publishes it; with tilts, measures them from focus sweeps. REP `:5561`, "
                                   "PUB `:5560`.")

#: Uploads travel base64-encoded inside the request (PNG or TIFF).
Base64 = Annotated[str, Field(min_length=1, max_length=96 * 2**20)]


class TeachRequest(CommandRequest):
    """One source of the reference: the live frame(s) (default), an image (upload or
    path), a polygon or a mask image drawn on the live frame (paper case 6)."""

    frames: int = Field(1, ge=1, le=16, description="average the last frames (the stage must stand still)")
    scanned_after_ns: int | None = Field(
        None, ge=0, description="live frames only if their scan began at or after this (Unix ns; the stage's "
                                "settled_at_ns): `not_enough_frames` until as many as asked have come")
    image_b64: Base64 | None = Field(None, description="a PNG/TIFF of the current scan's size")
    path: str | None = Field(None, max_length=4096, description="a PNG/TIFF on the estimator's machine")
    label: str | None = Field(None, max_length=500)
    polygon: list[Annotated[list[float], Field(min_length=2, max_length=2)]] | None = Field(
        None, min_length=3, max_length=1000, description="[[x, y], ...] corner points on the live frame")
    mask_b64: Base64 | None = Field(None, description="a binary PNG/TIFF mask of the current scan's size")
    tilts: bool = Field(False, description="also sweep the focus at the taught pose (in the background: the reply "
                                           "comes at once, `tilt_teach` in `report` says how far it is)")
    source_interval_s: list[float] | None = Field(None, min_length=2, max_length=2,
                                                  description="with an image: when it was scanned on the source's "
                                                              "clock (a one-off slow scan)")


#: The focus measures a teach's sweeps can be read by (``SEMSERVO_ESTIMATOR__TILT_FOCUS_MEASURE``;
#: :data:`semservo.estimation.tilt.FOCUS_MEASURES`, the science's own list, is the same).
FocusMeasure = Literal["normalized_variance", "gradient"]


class TiltTeach(CommandReply):
    """The taught pose's focus sweeps, which run after a teach with tilts: one, or more of
    the same view pooled while they pin the tilts loosely."""

    state: Literal["sweeping", "done", "failed"]
    reference_id: str
    scanned: int = 0
    frames: int = 0
    sweep: int = Field(1, description="which sweep is scanning (or the last one), from 1")
    max_sweeps: int = Field(1, description="the most sweeps the teach takes before it refuses")
    fine: bool = Field(False, description="the wide sweeps could not pin the tilts: these sweep the view finely, a "
                                          "quarter of a depth of field apart, about the depths they found")
    wide_sweeps: int = Field(0, description="fine: how many wide sweeps came before the fine ones (sweep and "
                                            "max_sweeps count both)")
    focus_measure: FocusMeasure = Field(
        "normalized_variance", description="the focus measure the sweeps are read by: eq. 13 or the gradient energy")
    pinned_deg: list[float] | None = Field(None, description="the standard errors of alpha and beta (degrees) from "
                                                             "the sweeps so far, pooled")
    error: str | None = None
    code: str | None = Field(None, description="failed: sweep_failed, or no_tilt_reference (the sweep cannot tell "
                                               "the tilts)")


class Reference(CommandReply):
    """The taught reference, as the estimator holds it."""

    id: str
    kind: Literal["frame", "image", "mask"]
    shape: list[int]
    pixel_size_nm: float | None
    taught_at_ns: int
    acquisition: dict[str, Any] = Field(default_factory=dict, description="what its source says of the acquisition "
                                                                          "(pixel size, magnification, dwell, ...)")
    frame_seq: int | None = None
    source: str | None = None
    frames_averaged: int | None = None
    source_interval_s: list[float] | None = Field(None, description="when it was scanned, on the source's clock")
    label: str | None = None
    polygon: list[list[float]] | None = None
    tilt: dict[str, Any] | None = Field(None, description="the taught pose's sweeps: alpha_deg, beta_deg of its plane, "
                                                          "centre_um, kernels_used, frames (of each sweep), sweeps "
                                                          "(pooled), alpha_uncertainty_deg, beta_uncertainty_deg, "
                                                          "content_moved_px (per sweep, how far its content moved "
                                                          "while it scanned, its frames moved back by it; null: not "
                                                          "steadied)")
    tilt_teach: TiltTeach | None = None
    vibration: dict[str, Any] | None = Field(None, description="the stage's vibration lines, learned from the frames "
                                                               "at rest when it was taught, that each scan-averaged "
                                                               "shift fits: state (learning, learned, none), lines_hz, "
                                                               "frames (at rest, used), reason (when none)")


class ClearReply(CommandReply):
    cleared: bool


class Report(CommandReply):
    reference: Reference | None
    rotation: bool = Field(description="rotation is measured in this estimator's configuration")
    measure_rotation: bool
    measure_tilts: bool
    tilt_reference: dict[str, Any] | None
    last_tilt: dict[str, Any] | None
    tilt_error: str | None
    precision: str
    latest_frame_seq: int | None
    last_estimate: dict[str, Any] | None


class MeasureRequest(CommandRequest):
    rotation: bool | None = Field(None, description="measure each frame's rotation (null: as configured)")
    tilts: bool | None = Field(None, description="measure the tilts, one focus sweep after another (null: not)")


class MeasureReply(CommandReply):
    rotation: bool
    tilts: bool


class TiltedRequest(CommandRequest):
    settles_at_ns: int | None = Field(None, ge=0, le=2**63 - 1,
                                      description="when the tilt move arrives (Unix ns, the stage's settled_at_ns; "
                                                  "null: now)")


class TiltedReply(CommandReply):
    restarted: bool = Field(description="the tilts were being measured: the sweep in progress (if any) is cancelled, "
                                        "and the next starts once the tilt has settled")


class MovedRequest(CommandRequest):
    settles_at_ns: int = Field(ge=0, le=2**63 - 1, description="when the move has settled (Unix ns, the stage's "
                                                               "settled_at_ns)")


class MovedReply(CommandReply):
    partial_from_ns: int | None = Field(description="frames whose scan spans this time are measured on the rows "
                                                    "scanned after it (null: no reference, nothing to measure)")


class ReferenceImageRequest(CommandRequest):
    id: str | None = Field(None, max_length=64, description="only if it is still this reference")


class ReferenceImage(CommandReply):
    id: str
    dtype: str
    shape: list[int]
    pixels_b64: str = Field(description="the reference's pixels, raw, row-major, base64")


TEACH = COMMANDS.add("teach", TeachRequest, Reference,
                     "teach the reference (a refused teach keeps the previous one; `not_enough_frames` while fewer "
                     "frames have arrived than asked to average)", timeout_s=60.0)
CLEAR = COMMANDS.add("clear", NoArguments, ClearReply, "forget the reference (nothing is published)")
# The estimator serves its socket between frames: just after a teach (a new reference's
# transforms planned, its focus sweeps' planes fitted in another thread) on a busy
# machine, its report came past 1 s, to the controller's run start and to the gateway's
# teach (which asks it first, to name a dead estimator in seconds, not after 60 s): both
# refused for nothing, the teach as a 503 in CI. So every caller gives it 5 s.
REPORT = COMMANDS.add("report", NoArguments, Report, "the reference, what is measured, the last tilt measurement",
                      timeout_s=5.0)
MEASURE = COMMANDS.add("measure", MeasureRequest, MeasureReply,
                       "what to measure per frame (a run without the rotation DOF skips it; a run with the tilts "
                       "starts the tilt tracker: `no_tilt_reference` without a taught sweep)")
TILTED = COMMANDS.add("tilted", TiltedRequest, TiltedReply,
                      "the sample was tilted (a run's tilt move): the focus sweep in progress, whose frames show "
                      "poses in between, is cancelled and the next starts once the tilt has settled")
MOVED = COMMANDS.add("moved", MovedRequest, MovedReply,
                     "the stage moved (a run's move), settling at settles_at_ns: the frame whose scan spans that "
                     "time is measured on its rows scanned after it (a partial frame, `first_row` in its estimate), "
                     "when they are at least half of them and its source times its scans (`source_interval_s`); "
                     "a run acts on it a scan sooner than on the next whole frame. Best effort, so answered within "
                     "0.25 s or given up (that frame is then used whole)", timeout_s=0.25)
REFERENCE_IMAGE = COMMANDS.add("reference_image", ReferenceImageRequest, ReferenceImage,
                               "the taught reference's pixels (`no_reference`)", timeout_s=5.0)
