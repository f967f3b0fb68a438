"""The image server's command handlers (declared in :mod:`semservo.protocol.imageserver`):
functions of an :class:`ImageServer` and a checked request, testable without a socket.
What a source can do is asked of the source (:func:`semservo.instruments.capabilities`),
never of its class."""

from __future__ import annotations

import base64
import io
from dataclasses import dataclass, field

from PIL import Image

from semservo.errors import BadRequest, CommandError
from semservo.instruments import NotSupported, SourceUnavailable, capabilities
from semservo.protocol import Handlers, NoArguments, OpenReply
from semservo.protocol import imageserver as protocol
from services.imageserver.core import ImageServerCore
from services.imageserver.sources import focus_session, set_scan
from services.imageserver.sweep import FocusSweeps


@dataclass
class ImageServer:
    """What the handlers work on: the core (its source, pace and numbering), where the
    frames go, and the focus sweeps (on a source that can focus)."""

    core: ImageServerCore
    frames_endpoint: str = ""
    published: object = lambda: 0  # frames published so far (the publisher's count)
    sweeps: FocusSweeps | None = field(default=None)

    def __post_init__(self):
        if self.sweeps is None and "focus" in capabilities(self.core.source):
            self.sweeps = FocusSweeps(lambda: focus_session(self.core.source))

    @property
    def source(self):
        return self.core.source

    def close(self) -> None:
        if self.sweeps is not None:
            self.sweeps.close()


handlers: Handlers[ImageServer] = Handlers(protocol.COMMANDS)


def _not_supported(error: Exception) -> CommandError:
    return CommandError("not_supported", str(error))


@handlers.handles(protocol.INFO)
def info(server: ImageServer, _request: NoArguments) -> OpenReply:
    return OpenReply.model_validate({**server.source.describe(), "fps": server.core.pacer.fps,
                                     "frames_endpoint": server.frames_endpoint, "published": server.published(),
                                     "next_seq": server.core.seq,
                                     "capabilities": sorted(capabilities(server.source))})


@handlers.handles(protocol.SET_FPS)
def set_fps(server: ImageServer, request: protocol.SetFpsRequest) -> protocol.FpsReply:
    server.core.set_fps(request.fps)
    return protocol.FpsReply(fps=server.core.pacer.fps)


@handlers.handles(protocol.SET_SCAN)
def set_scan_settings(server: ImageServer, request: protocol.SetScanRequest) -> OpenReply:
    values = request.model_dump(exclude_none=True)
    if not values:
        raise BadRequest("set_scan needs dwell_ns, magnification, working_distance_mm or working_distance_um")
    try:
        return OpenReply.model_validate(set_scan(server.source, **values))
    except NotSupported as error:
        raise _not_supported(error) from None
    except ValueError as error:  # the source refused the value
        raise BadRequest(f"scan settings: {error}") from None


@handlers.handles(protocol.SCAN_ONCE)
def scan_once(server: ImageServer, request: protocol.ScanOnceRequest) -> protocol.ScanOnceReply:
    """One frame scanned with other settings (e.g. a slow dwell for a high-quality
    reference, paper case 5), as a 16-bit PNG in base64 with its acquisition; the stream
    goes on with the usual settings."""
    if "scan_once" not in capabilities(server.source):
        raise CommandError("not_supported", f"the {server.source.name} source cannot scan one frame with other "
                                            "settings (a replay or a watched folder only has what was saved)")
    target = getattr(server.source, "inner", server.source)
    try:
        image = target.scan_once(dwell_ns=request.dwell_ns, magnification=request.magnification)
    except ValueError as error:
        raise BadRequest(f"scan settings: {error}") from None
    except SourceUnavailable as error:
        raise CommandError("scan_failed", str(error)) from None
    buffer = io.BytesIO()
    Image.fromarray(image.pixels).save(buffer, format="PNG")
    return protocol.ScanOnceReply(
        image_b64=base64.b64encode(buffer.getvalue()).decode(), dwell_ns=image.dwell_ns,
        magnification=image.magnification, pixel_size_nm=image.pixel_size_nm,
        source_interval_s=list(image.source_interval_s) if image.source_interval_s else None)


def _focus_sweeps(server: ImageServer) -> FocusSweeps:
    """The server's focus sweeps; ``not_supported`` for a source that cannot focus."""
    if server.sweeps is None:
        raise CommandError("not_supported", f"focus sweeps need a source that can focus; the {server.source.name} "
                                            "source cannot")
    return server.sweeps


def _sweep_reply(state) -> protocol.SweepReply:
    """A sweep's state as the reply; ``no_such_sweep`` for one that is not the last."""
    try:
        return protocol.SweepReply.model_validate(state())
    except KeyError as error:
        raise CommandError("no_such_sweep", str(error.args[0])) from None


@handlers.handles(protocol.START_SWEEP)
def start_sweep(server: ImageServer, request: protocol.StartSweepRequest) -> protocol.SweepStarted:
    """Scan the field at each working distance (um offsets from the focus now, larger
    deeper) in the background; fetch the frames with ``sweep``."""
    sweeps = _focus_sweeps(server)
    try:
        return protocol.SweepStarted.model_validate(sweeps.start(request.working_distances_um))
    except ValueError as error:
        raise BadRequest(str(error)) from None
    except RuntimeError as error:
        raise CommandError("busy", str(error)) from None


@handlers.handles(protocol.SWEEP)
def sweep(server: ImageServer, request: protocol.SweepRequest) -> protocol.SweepReply:
    sweeps = _focus_sweeps(server)
    return _sweep_reply(lambda: sweeps.result(request.sweep_id))


@handlers.handles(protocol.CANCEL_SWEEP)
def cancel_sweep(server: ImageServer, request: protocol.SweepRequest) -> protocol.SweepReply:
    """Stop a sweep whose frames will not be used, after the scan in progress."""
    sweeps = _focus_sweeps(server)
    return _sweep_reply(lambda: sweeps.cancel(request.sweep_id))
