"""The estimator's command handlers (declared in :mod:`semservo.protocol.estimator`):
functions of an :class:`Estimator` (the core and its tilt tracker) and a checked
request, testable without a socket."""

from __future__ import annotations

import base64
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from semservo.errors import CommandError
from semservo.imagefiles import ImageFileError, read_image
from semservo.protocol import Handlers, NoArguments
from semservo.protocol import estimator as protocol
from services.estimator.core import EstimatorCore, TeachError, decode_upload
from services.estimator.tilts import TiltTracker

log = logging.getLogger("estimator")


@dataclass
class Estimator:
    """What the handlers work on: the core, and the tracker that runs focus sweeps (None
    where the estimator cannot ask for sweeps)."""

    core: EstimatorCore
    tracker: TiltTracker | None = None

    def taught(self, reference: dict) -> dict:
        log.info("taught reference %s (%s)", reference["id"], reference["kind"])
        return reference


handlers: Handlers[Estimator] = Handlers(protocol.COMMANDS)


def _read_path(path: str) -> tuple[np.ndarray, dict]:
    try:
        pixels, metadata = read_image(Path(path))
    except ImageFileError as error:
        raise TeachError(str(error)) from None
    return pixels, metadata


@handlers.handles(protocol.TEACH)
def teach(estimator: Estimator, request: protocol.TeachRequest) -> protocol.Reference:
    core, tracker = estimator.core, estimator.tracker
    sources = [name for name in ("image_b64", "path", "polygon", "mask_b64") if getattr(request, name) is not None]
    if len(sources) > 1:
        raise TeachError(f"give one source of the reference, not {' and '.join(sources)}")
    if request.tilts and sources and sources != ["path"] and sources != ["image_b64"]:
        raise TeachError("tilts are taught at the live pose (a focus sweep), not with a mask")
    if request.tilts and tracker is None:
        raise CommandError("no_sweeps", "this estimator cannot ask for focus sweeps: tilts cannot be taught")
    if request.tilts and core.measure_tilts:
        raise CommandError("busy", "a run is measuring the tilts (focus sweeps): stop it first")
    sweep_frames = len(core.next_sweep()) if request.tilts else 0  # refused here, before anything is taught
    if request.image_b64 is not None:
        pixels, metadata = decode_upload(request.image_b64, with_metadata=True)
        reference = core.teach_image(pixels, label=request.label or "upload", acquisition=metadata,
                                     source_interval_s=request.source_interval_s)
    elif request.path is not None:
        pixels, metadata = _read_path(request.path)
        reference = core.teach_image(pixels, label=request.label or request.path, acquisition=metadata)
    elif request.polygon is not None:
        reference = core.teach_mask(polygon=request.polygon)
    elif request.mask_b64 is not None:
        # A mask is drawn at the scan's size and has no data bar: its black-and-white
        # bottom rows looked like one (a full-scale overlay) and were cropped.
        reference = core.teach_mask(mask=decode_upload(request.mask_b64, data_bar=0))
    else:
        reference = core.teach_latest(frames=request.frames, scanned_after_ns=request.scanned_after_ns)
    if request.tilts:  # the taught pose's focus sweep, now, before anything moves: in the background
        tracker.teach(reference["id"], frames=sweep_frames)
    elif tracker is not None:
        tracker.teach_cancel()
    return protocol.Reference.model_validate(estimator.taught(core.describe_reference()))


@handlers.handles(protocol.CLEAR)
def clear(estimator: Estimator, _request: NoArguments) -> protocol.ClearReply:
    if estimator.tracker is not None:
        estimator.tracker.teach_cancel()
    return protocol.ClearReply.model_validate(estimator.core.clear())


@handlers.handles(protocol.REPORT)
def report(estimator: Estimator, _request: NoArguments) -> protocol.Report:
    return protocol.Report.model_validate(estimator.core.report())


@handlers.handles(protocol.MEASURE)
def measure(estimator: Estimator, request: protocol.MeasureRequest) -> protocol.MeasureReply:
    result = estimator.core.measure(request.rotation, request.tilts)
    if estimator.tracker is not None:
        estimator.tracker.wake()
    return protocol.MeasureReply.model_validate(result)


@handlers.handles(protocol.TILTED)
def tilted(estimator: Estimator, request: protocol.TiltedRequest) -> protocol.TiltedReply:
    restarted = estimator.tracker.tilted(request.settles_at_ns) if estimator.tracker is not None else False
    return protocol.TiltedReply(restarted=restarted)


@handlers.handles(protocol.MOVED)
def moved(estimator: Estimator, request: protocol.MovedRequest) -> protocol.MovedReply:
    return protocol.MovedReply.model_validate(estimator.core.moved(request.settles_at_ns))


@handlers.handles(protocol.REFERENCE_IMAGE)
def reference_image(estimator: Estimator, request: protocol.ReferenceImageRequest) -> protocol.ReferenceImage:
    core = estimator.core
    if core.reference is None or core.reference_pixels is None:
        raise CommandError("no_reference", "no reference is taught")
    if request.id is not None and request.id != core.reference.id:
        raise CommandError("no_reference", f"reference {request.id} is not the taught one ({core.reference.id})")
    pixels = np.ascontiguousarray(core.reference_pixels)
    return protocol.ReferenceImage(id=core.reference.id, dtype=str(pixels.dtype), shape=list(pixels.shape),
                                   pixels_b64=base64.b64encode(pixels.tobytes()).decode())
