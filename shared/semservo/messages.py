"""Typed, versioned messages that cross process boundaries (pydantic v2).

Two kinds of traffic:

* **Frames** travel PUB/SUB as three-part ZeroMQ messages ``[topic, header, pixels]``
  (see :mod:`semservo.wire`); :class:`FrameHeader` is the JSON header.
* **Commands** travel request-reply as one JSON part: a :class:`Request` answered by a
  :class:`Reply`. Every service answers the ``health`` command with a :class:`Health`.

Every message carries ``v``, the wire version; a receiver drops any other version.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, PositiveInt

from semservo.sem_metadata import ImageMetadata

WIRE_VERSION = 1

#: Pixel types a frame may carry, little-endian on the wire.
PixelType = Literal["uint8", "uint16", "float32"]
PIXEL_DTYPES: dict[str, np.dtype] = {
    "uint8": np.dtype("u1"),
    "uint16": np.dtype("<u2"),
    "float32": np.dtype("<f4"),
}

FRAME_TOPIC = b"frame"
MOTION_TOPIC = b"motion"


class _Message(BaseModel):
    # No NaN or infinity anywhere on the wire: a number that is not finite is a
    # malformed message, dropped and counted like any other.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    v: Literal[1] = WIRE_VERSION


class FrameHeader(_Message):
    """What a frame says about itself. The pixels follow as a separate raw part."""

    seq: int = Field(ge=0, description="sequence number, +1 per published frame")
    acquired_at_ns: int = Field(ge=0, description="Unix time (ns) the scan finished")
    published_at_ns: int = Field(ge=0, description="Unix time (ns) the frame was handed to the socket")
    shape: tuple[PositiveInt, PositiveInt] = Field(description="(rows, columns)")
    dtype: PixelType
    # What the source knows of the acquisition; None: not known (never a made-up value).
    pixel_size_nm: PositiveFloat | None = Field(None, description="pixel size on the sample, P = D / G (eq. 43)")
    magnification: PositiveFloat | None = None
    dwell_ns: PositiveFloat | None = Field(None, description="dwell time per pixel")
    working_distance_mm: PositiveFloat | None = Field(None, description="working distance (focus)")
    high_voltage_kv: PositiveFloat | None = Field(None, description="accelerating voltage")
    detector: str | None = Field(None, max_length=200, description="e.g. 'SE', 'ETD', 'InLens'")
    instrument: str | None = Field(None, max_length=200, description="vendor and model, e.g. 'TESCAN MIRA3 XMU'")
    data_bar_rows: int | None = Field(None, ge=0, description="rows of data bar cropped from the file's image")
    source: str = Field(min_length=1, max_length=200, description="which source made it, e.g. 'replay'")
    label: str | None = Field(None, max_length=500, description="source-specific name, e.g. the file")
    scan_started_at_ns: int | None = Field(
        None, ge=0, description="Unix time (ns) the scan began: a frame shows a move only if it began after it")
    source_interval_s: tuple[float, float] | None = Field(
        None, description="the scan's start and end on the source's own clock (the fake lab's simulated time)")

    @property
    def nbytes(self) -> int:
        return self.shape[0] * self.shape[1] * PIXEL_DTYPES[self.dtype].itemsize


#: The acquisition fields of a :class:`FrameHeader`: what a file or a source may know.
ACQUISITION_FIELDS = tuple(field.name for field in dataclasses.fields(ImageMetadata))


class Request(_Message):
    """A command to a service's control socket."""

    command: str = Field(min_length=1, max_length=64)
    args: dict[str, Any] = Field(default_factory=dict)


class ErrorBody(BaseModel):
    model_config = ConfigDict(frozen=True)

    code: str
    message: str
    details: dict[str, Any] | None = None  # e.g. the id of the run that is in the way


class Reply(_Message):
    """The answer to a :class:`Request`: a result, or an error with a code and words."""

    ok: bool
    result: dict[str, Any] | None = None
    error: ErrorBody | None = None

    @classmethod
    def success(cls, result: dict[str, Any] | None = None) -> "Reply":
        return cls(ok=True, result=result or {})

    @classmethod
    def failure(cls, code: str, message: str, details: dict[str, Any] | None = None) -> "Reply":
        return cls(ok=False, error=ErrorBody(code=code, message=message, details=details or None))


ServiceState = Literal["starting", "running", "idle", "finished", "degraded", "stopping"]


class Health(BaseModel):
    """What every service reports on its control socket."""

    model_config = ConfigDict(frozen=True)

    service: str
    state: ServiceState
    pid: int
    uptime_s: float
    counters: dict[str, int]
    last_error: str | None = None
    details: dict[str, Any] = Field(default_factory=dict)

    @property
    def healthy(self) -> bool:
        return self.state in ("running", "idle", "finished")


class MotionEstimate(_Message):
    """What the estimator publishes for each frame it measured (topic ``motion``).

    Sign convention as :mod:`semservo.estimation`: content displacement of the current
    frame against the taught reference, x right, y down, rotation counter-clockwise as
    displayed.
    """

    seq: int = Field(ge=0, description="the frame's sequence number")
    reference_id: str
    dx_px: float
    dy_px: float
    rotation_deg: float
    confidence: float = Field(ge=0, le=1)
    snr_db: float
    filtered: bool
    pixel_size_nm: PositiveFloat | None = Field(description="the frame's; None when its source does not know it")
    frame_acquired_at_ns: int = Field(ge=0)
    frame_published_at_ns: int = Field(ge=0)
    frame_scan_started_at_ns: int | None = Field(None, ge=0, description="the frame's scan_started_at_ns")
    frame_source_interval_s: tuple[float, float] | None = Field(None, description="the frame's source_interval_s")
    published_at_ns: int = Field(ge=0, description="Unix time (ns) this estimate was sent")
    estimation_ms: float = Field(ge=0, description="time spent estimating")
    scan_averaged: bool = Field(False, description="the shift was averaged over the scan's bands of rows "
                                                   "(semservo.estimation.raster)")
    latency_ms: float = Field(description="frame published -> estimate published")
    first_row: int = Field(0, ge=0, description="a partial frame: the first of the frame's rows measured (0: the "
                                                "whole frame); the rows above were scanned while the stage still "
                                                "moved (the estimator's `moved`)")
    rows_scanned_from_ns: int | None = Field(None, ge=0, description="a partial frame: when its first measured row's "
                                                                      "scan began (Unix ns)")
    rows_source_interval_s: tuple[float, float] | None = Field(
        None, description="a partial frame: when its measured rows were scanned, on the source's clock")
    # The latest tilt measurement (focus sweep) against the reference, while tilts are
    # measured: alpha about x, beta about y (degrees, :mod:`semservo.estimation.tilt`'s convention).
    alpha_deg: float | None = None
    beta_deg: float | None = None
    tilt_confidence: float | None = Field(None, ge=0, le=1)
    tilt_seq: int | None = Field(None, ge=0, description="which sweep: a new number is a new measurement")
    tilt_scan_started_at_ns: int | None = Field(None, ge=0, description="when that sweep's first scan began")
    tilt_frames: int | None = Field(None, ge=0, description="frames that sweep took")
    tilt_sweep_s: float | None = Field(None, ge=0, description="wall time that sweep took")
    tilt_source_interval_s: tuple[float, float] | None = Field(None, description="that sweep on the source's clock")
    tilt_reason: str | None = Field(None, max_length=2000,
                                    description="why that sweep could not tell the tilts (its confidence 0)")
    tilt_uncertainty_deg: tuple[float, float] | None = Field(
        None, description="that sweep's standard errors of alpha, beta (degrees; the taught sweep's not included: "
                          "a constant offset no further sweep averages away)")


class ScanRequest(_Message):
    """What the image server's ``sim`` source asks the simulated SEM for, as it would
    command a real scan generator. ``None`` keeps the fake lab's preset value."""

    dwell_ns: PositiveFloat | None = Field(None, le=1e6, description="ns per pixel (1 ms at most)")
    magnification: PositiveFloat | None = Field(None, le=1e7)
    working_distance_um: float | None = Field(None, ge=-1e5, le=1e5, description="focus: the working distance's "
                                              "offset from the nominal one (um, larger deeper)")
    aperture_um: PositiveFloat | None = Field(None, ge=5, le=2000, description="objective aperture diameter (um): "
                                              "with the working distance, the beam half-angle and depth of field")
    brightness: float = Field(0.0, ge=-1, le=1)
    contrast: float = Field(1.0, gt=0, le=10)
    rows: int = Field(512, ge=64, le=4096)
    cols: int = Field(512, ge=64, le=4096)
    bit_depth: Literal[8, 16] = 8


CONTROLLER_TOPIC = b"controller"


class ControllerEvent(_Message):
    """What the controller publishes (topic ``controller``): its status whenever it
    changes, and every iteration's record as it happens."""

    kind: Literal["status", "iteration"]
    run_id: str | None = None
    data: dict[str, Any] = Field(default_factory=dict)
