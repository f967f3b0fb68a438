"""The image server's commands (``services/imageserver``): the frame stream's rate and
scan settings, one-off scans, focus sweeps. What a source cannot do (a replayed folder
cannot focus) is refused with ``not_supported`` in words.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, PositiveFloat

from semservo.protocol import CommandReply, CommandRequest, CommandSet, NoArguments, OpenReply

COMMANDS = CommandSet("imageserver", "Acquires SEM frames from a source (the simulated SEM, a replayed folder, the "
                                     "folder an SEM saves into, a lab's adapter) and streams them on PUB `:5550`. "
                                     "REP `:5551`.")

#: The most frames one sweep may ask for (a sweep of 60 frames is minutes of scanning).
MAX_SWEEP_FRAMES = 60


class SetFpsRequest(CommandRequest):
    fps: PositiveFloat = Field(le=10_000, description="frames per second")


class FpsReply(CommandReply):
    fps: float


class SetScanRequest(CommandRequest):
    """The frames that follow, on a source that can (the simulated SEM: dwell,
    magnification and its focus offset; a lab's adapter: what it implements)."""

    dwell_ns: PositiveFloat | None = Field(None, le=1e6)
    magnification: PositiveFloat | None = Field(None, le=1e7)
    working_distance_mm: PositiveFloat | None = Field(None, le=1000, description="an adapter's focus")
    working_distance_um: float | None = Field(None, ge=-1e4, le=1e4, description="the focus offset from the nominal "
                                                                                 "working distance (um, larger deeper)")


class ScanOnceRequest(CommandRequest):
    dwell_ns: PositiveFloat | None = Field(None, le=1e6, description="e.g. a slow dwell for a high-quality reference")
    magnification: PositiveFloat | None = Field(None, le=1e7)


class ScanOnceReply(CommandReply):
    image_b64: str = Field(description="the frame as a 16-bit PNG, base64")
    dwell_ns: float | None
    magnification: float | None
    pixel_size_nm: float | None
    source_interval_s: list[float] | None


class StartSweepRequest(CommandRequest):
    working_distances_um: list[float] = Field(min_length=3, max_length=MAX_SWEEP_FRAMES,
                                              description="focus offsets (um, larger deeper): increasing, evenly "
                                                          "spaced, |x| <= 1e4")


class SweepStarted(CommandReply):
    sweep_id: str
    state: Literal["scanning"]
    frames: int
    working_distances_um: list[float]


class SweepRequest(CommandRequest):
    sweep_id: str = Field(min_length=1, max_length=64)


class SweepReply(CommandReply):
    sweep_id: str
    state: Literal["scanning", "done", "failed"]
    scanned: int
    frames: int
    working_distances_um: list[float]
    error: str | None = None
    dtype: str | None = None
    shape: list[int] | None = None
    frames_b64: list[str] | None = Field(None, description="done: each frame's raw pixels, base64")
    pixel_size_nm: float | None = None
    magnification: float | None = None
    scan_started_at_ns: int | None = None
    acquired_at_ns: int | None = None
    frame_times_ns: list[int] | None = Field(None, description="done: the middle of each frame's scan (its acquisition "
                                                                "time where the scan's start is unknown), the clock of "
                                                                "the frames' headers")
    source_interval_s: list[float] | None = None
    took_s: float | None = None


INFO = COMMANDS.add("info", NoArguments, OpenReply, "the source (and its counts: a watched folder's files_*), fps, "
                                                    "frames endpoint, frames published")
SET_FPS = COMMANDS.add("set_fps", SetFpsRequest, FpsReply, "the stream's frame rate")
SET_SCAN = COMMANDS.add("set_scan", SetScanRequest, OpenReply, "scan settings of the frames that follow (what is "
                                                               "now set)")
SCAN_ONCE = COMMANDS.add("scan_once", ScanOnceRequest, ScanOnceReply,
                         "one frame with other scan settings, the stream unchanged (a source that can scan once)",
                         timeout_s=90.0)
START_SWEEP = COMMANDS.add("start_sweep", StartSweepRequest, SweepStarted,
                           "scan the field at each working distance, in the background (any source that can focus; "
                           "`busy` while one runs)")
CANCEL_SWEEP = COMMANDS.add("cancel_sweep", SweepRequest, SweepReply,
                            "stop a sweep after the scan in progress: it ends `failed` (cancelled), and the next may "
                            "start (`no_such_sweep`)", timeout_s=5.0)
SWEEP = COMMANDS.add("sweep", SweepRequest, SweepReply, "a sweep's state; its frames once done (`no_such_sweep`)",
                     timeout_s=10.0)

