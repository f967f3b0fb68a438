"""Frame sources. A source yields acquired images with their metadata; the image
server core paces, numbers and stamps them.

Every source has the same small interface (:class:`semservo.instruments.ImageSource`),
so a lab's adapter (:func:`adapter_source`), the simulated SEM (:class:`SimSource`) and
the watched folder (:class:`services.imageserver.watch.WatchSource`) plug in where
``replay`` sits.
"""

from __future__ import annotations

import contextlib
import inspect
import logging
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

import zmq

from semservo.config import pixel_size_nm
from semservo.imagefiles import DataBar, ImageFileError, list_frames, read_sem_image
from semservo.instruments import (IMAGE_SOURCE_GROUP, AcquiredImage, ImageSource, NotReady, NotSupported,
                                  SourceUnavailable, capabilities, load_plugin)
from semservo.sem_metadata import ImageMetadata
from semservo.messages import ACQUISITION_FIELDS, Reply, ScanRequest
from semservo.transport import ControlClient, RequestCancelled, ServiceUnavailable
from semservo.wire import WireError, decode_frame

__all__ = ["AcquiredImage", "BackgroundAcquisition", "FrameSource", "NotReady", "ReplaySource", "SimSource",
           "SourceUnavailable", "adapter_source", "focus_session", "merge_metadata", "set_scan"]

log = logging.getLogger("imageserver")


#: What the image server core asks of a source (the interface labs write against).
FrameSource = ImageSource


class ReplaySource:
    """Replays a folder of PNG or TIFF frames (8 or 16 bit) in name order.

    Acquisition metadata: the ``overrides`` (command-line options) over each file's own
    (:mod:`semservo.sem_metadata`) over the ``fallbacks`` (settings: what to assume
    when the files do not say). What none of them gives stays unknown, except the
    pixel size, which follows from a magnification the user gave, P = D / G (eq. 43).
    Data bars are cropped (``data_bar``). Every file is read and checked when the
    source is made, so a bad folder fails at start with the file named, not halfway
    through a run.
    """

    name = "replay"

    def __init__(
        self,
        folder: str | Path,
        *,
        pattern: str | None = None,
        loop: bool = True,
        overrides: dict | None = None,
        fallbacks: dict | None = None,
        data_bar: DataBar = "auto",
    ):
        self.folder = Path(folder)
        self.loop = loop
        self.paths = list_frames(self.folder, pattern or "*")
        #: Left out by default (no ``pattern``): the taught image a recording keeps beside
        #: its frames, ``reference.*`` (the 2013 run's reference.png is not one of its frames).
        self.left_out = [] if pattern else [path.name for path in self.paths if path.stem.lower() == "reference"]
        self.paths = [path for path in self.paths if path.name not in self.left_out]
        if not self.paths:
            raise FileNotFoundError(f"no PNG or TIFF frames matching {pattern or '*'!r} in {self.folder}")
        self.images: list[tuple[np.ndarray, ImageMetadata]] = []
        detected: dict[tuple[int, ...], int] = {}  # one crop per file shape for the whole replay
        for path in self.paths:
            image = read_sem_image(path, data_bar=data_bar, detected=detected)
            image.pixels.setflags(write=False)  # published zero-copy: nobody may change it
            self.images.append((image.pixels, image.metadata.updated(data_bar_rows=image.data_bar_rows or None)))
        first = self.images[0][0]
        for path, (pixels, _) in zip(self.paths, self.images):
            if pixels.shape != first.shape or pixels.dtype != first.dtype:
                raise ImageFileError(
                    f"{path}: {pixels.shape} {pixels.dtype} differs from {self.paths[0].name}'s "
                    f"{first.shape} {first.dtype}; a replay folder holds one kind of frame"
                )
        self.overrides = {key: value for key, value in (overrides or {}).items() if value is not None}
        self.fallbacks = {key: value for key, value in (fallbacks or {}).items() if value is not None}
        self.position = 0
        self.passes = 0

    def acquire(self) -> AcquiredImage | None:
        if self.position >= len(self.images):
            if not self.loop:
                return None
            self.position = 0
            self.passes += 1
        pixels, from_file = self.images[self.position]
        path = self.paths[self.position]
        self.position += 1
        metadata = merge_metadata(from_file, self.overrides, self.fallbacks, pixels.shape[1])
        return AcquiredImage(pixels=pixels, acquired_at_ns=time.time_ns(), label=path.name, **metadata)

    def describe(self) -> dict:
        pixels = self.images[0][0]
        return {
            "source": self.name,
            "folder": str(self.folder),
            "frames": len(self.paths),
            **({"left_out": self.left_out} if self.left_out else {}),
            "shape": list(pixels.shape),
            "dtype": str(pixels.dtype),
            "loop": self.loop,
            "position": self.position,
            "passes": self.passes,
        }


def merge_metadata(from_file: ImageMetadata, overrides: dict, fallbacks: dict, width_px: int) -> dict:
    """The acquisition fields of a frame: ``overrides`` over the file's over
    ``fallbacks``; the pixel size from a magnification the user gave (P = D / G, eq. 43)
    when neither the user nor the file gives it. Unknown fields are left out."""
    merged = {**fallbacks, **from_file.known(), **overrides}
    user_magnification = overrides.get("magnification") or (
        None if from_file.magnification is not None else fallbacks.get("magnification"))
    if user_magnification and ("pixel_size_nm" not in overrides) and (
            "pixel_size_nm" not in merged or "magnification" in overrides):
        merged["pixel_size_nm"] = pixel_size_nm(user_magnification, width_px)
    return merged


class BackgroundAcquisition:
    """Runs a blocking source (a scan takes a frame time) in a thread of its own, so the
    service's sockets, health above all, stay responsive while a frame is acquired.

    :meth:`acquire` never blocks: it returns the newest frame the thread has, raises
    :class:`NotReady` when there is none yet, and re-raises the thread's last source
    error once, even when a frame came after it (a frame first, the error at the next
    call). The thread paces itself at ``fps`` at most.
    """

    def __init__(self, source, fps: float, notify: Callable[[], None] | None = None):
        self.source = source
        self.name = source.name
        # The sources here take ``cancelled`` (asked while they wait); a lab's adapter need not.
        self._takes_cancel = "cancelled" in inspect.signature(source.acquire).parameters
        self.fps = fps
        #: Told (from the acquisition thread) when a frame or an error is ready: the image
        #: server then wakes, instead of asking again and again.
        self.notify = notify or (lambda: None)
        self._latest: AcquiredImage | None = None
        self._last_published: AcquiredImage | None = None
        self._error: Exception | None = None
        self._ended = False
        self._lock = threading.Lock()
        #: Held around each acquisition; a focus sweep on a source that scans one thing at a
        #: time holds it for the whole sweep (the stream pauses).
        self.instrument = threading.RLock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"acquire-{source.name}", daemon=True)
        self._thread.start()

    def capabilities(self) -> set[str]:
        return capabilities(self.source)

    @property
    def inner(self):
        """The source this acquisition runs."""
        return self.source

    @property
    def last_image(self) -> AcquiredImage | None:
        """The last frame handed out (its acquisition: e.g. the working distance)."""
        return self._last_published

    def _run(self) -> None:
        next_due = time.monotonic()
        while not self._stop.is_set():
            wait = next_due - time.monotonic()
            if wait > 0 and self._stop.wait(wait):
                return
            next_due = max(next_due + 1.0 / self.fps, time.monotonic())
            try:
                with self.instrument:
                    if self._stop.is_set():
                        return
                    image = self.source.acquire(cancelled=self._stop.is_set) if self._takes_cancel \
                        else self.source.acquire()
            except NotReady:
                if self._stop.is_set():  # cancelled: we are stopping
                    return
                continue
            except SourceUnavailable as error:
                with self._lock:
                    self._error = error
                self.notify()
                self._stop.wait(1.0)
                continue
            except Exception as error:  # noqa: BLE001 - a lab's adapter may fail any way: say so, keep going
                log.exception("the %s source failed", self.name)
                with self._lock:
                    self._error = SourceUnavailable(f"the {self.name} source failed: {type(error).__name__}: {error}")
                self.notify()
                self._stop.wait(1.0)
                continue
            if image is None:  # the source has ended
                with self._lock:
                    self._ended = True
                self.notify()
                return
            with self._lock:
                self._latest = image  # an error not yet reported stays: acquire raises it next
            self.notify()

    def acquire(self) -> AcquiredImage | None:
        with self._lock:
            image, error, ended = self._latest, self._error, self._ended
            if image is not None:
                self._latest = None  # the error, if any, is raised at the next call: never lost
            else:
                self._error = None
        if image is not None:
            self._last_published = image
            return image
        if error is not None:
            raise error
        if ended:
            return None
        raise NotReady

    def describe(self) -> dict:
        return self.source.describe()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=15)
        if hasattr(self.source, "close"):
            self.source.close()


class SimSource:
    """Frames from the simulated SEM of the fake lab, requested with scan settings as a
    real scan generator would be commanded (request-reply, one frame per request, over
    the lazy-pirate :class:`~semservo.transport.ControlClient`).

    A request that gets no frame in time raises :class:`SourceUnavailable`; the client
    then replaces its socket so the next request starts clean. In time: ``timeout_s``
    until scans have been timed, then five times the typical scan (at least a second).
    A request in flight when the fake lab died is never answered, and the restarted lab
    must not wait the whole ``timeout_s`` for a slow scan's sake.
    """

    #: A request this many times longer than the typical scan is taken as lost.
    OVERDUE_FACTOR = 5.0

    name = "sim"

    def capabilities(self) -> set[str]:
        return {"scan_settings", "focus", "focus_offset", "focus_beside_stream", "scan_once"}

    def __init__(self, endpoint: str, request: ScanRequest, *, timeout_s: float = 10.0,
                 max_message_bytes: int = 64 * 2**20, context: zmq.Context | None = None):
        self.endpoint = endpoint
        self.request = request
        self.max_message_bytes = max_message_bytes
        self.client = ControlClient(endpoint, timeout_s=timeout_s, retries=1, context=context,
                                    max_message_bytes=max_message_bytes)
        self.timeout_s = timeout_s
        self.typical_scan_s: float | None = None  # wall time of a scan round trip, smoothed
        self.frames = 0

    def _timeout(self) -> float:
        if self.typical_scan_s is None:
            return self.timeout_s
        return min(self.timeout_s, max(1.0, self.OVERDUE_FACTOR * self.typical_scan_s))

    def acquire(self, cancelled=None) -> AcquiredImage:
        """One frame; ``cancelled`` (asked while waiting) abandons the request and
        raises :class:`NotReady`."""
        return self.acquire_with(self.request, cancelled)

    def scan_at_focus(self, offset_um: float, nominal_mm: float | None = None) -> AcquiredImage:
        """One frame focused ``offset_um`` from the nominal working distance (the
        simulated SEM's focus offset): a frame of a focus sweep. The simulated SEM
        scans it beside the stream, on a socket of its own (sweeps run in their own
        thread)."""
        request = self.request.model_copy(update={"working_distance_um": offset_um})
        return self._acquire(request, self._side_client(), timeout_s=max(self.timeout_s, 60.0))

    def scan_once(self, *, dwell_ns: float | None = None, magnification: float | None = None) -> AcquiredImage:
        """One frame with other scan settings (a slow dwell for a high-quality
        reference, paper case 5); the stream goes on with its own."""
        changes = {key: value for key, value in (("dwell_ns", dwell_ns), ("magnification", magnification))
                   if value is not None}
        request = ScanRequest.model_validate({**self.request.model_dump(), **changes})
        client = ControlClient(self.endpoint, timeout_s=max(self.timeout_s, 60.0), retries=1,
                               max_message_bytes=self.max_message_bytes)
        try:
            return self._acquire(request, client, timeout_s=max(self.timeout_s, 60.0))
        finally:
            client.close()

    def _side_client(self) -> ControlClient:
        if getattr(self, "_sweep_client", None) is None:
            self._sweep_client = ControlClient(self.endpoint, timeout_s=max(self.timeout_s, 60.0), retries=1,
                                               max_message_bytes=self.max_message_bytes)
        return self._sweep_client

    def acquire_with(self, request: ScanRequest, cancelled=None) -> AcquiredImage:
        """One frame scanned with ``request`` (e.g. at another working distance)."""
        return self._acquire(request, self.client, self._timeout(), cancelled)

    def _acquire(self, request: ScanRequest, client: ControlClient, timeout_s: float, cancelled=None) -> AcquiredImage:
        started = time.monotonic()
        try:
            parts = client.request_parts(request.model_dump_json().encode(), timeout_s=timeout_s,
                                         cancelled=cancelled)
        except RequestCancelled:
            raise NotReady from None
        except ServiceUnavailable as error:
            # Lost, or scans got slower (another dwell): the next request waits the full time.
            self.typical_scan_s = None
            raise SourceUnavailable(f"no frame from the fake lab: {error}") from None
        if len(parts) == 1:
            reply = Reply.model_validate_json(parts[0].bytes)
            raise SourceUnavailable(f"the fake lab refused the scan: {reply.error.message if reply.error else reply}")
        try:
            frame = decode_frame(parts, max_bytes=self.max_message_bytes)
        except WireError as error:
            raise SourceUnavailable(f"malformed frame from the fake lab: {error}") from None
        self.frames += 1
        took = time.monotonic() - started
        self.typical_scan_s = took if self.typical_scan_s is None else 0.8 * self.typical_scan_s + 0.2 * took
        header = frame.header
        known = {key: getattr(header, key) for key in ACQUISITION_FIELDS if getattr(header, key) is not None}
        return AcquiredImage(pixels=frame.pixels, acquired_at_ns=header.acquired_at_ns or header.published_at_ns,
                             label=header.label, scan_started_at_ns=header.scan_started_at_ns,
                             source_interval_s=header.source_interval_s, **known)

    def describe(self) -> dict:
        return {"source": self.name, "endpoint": self.endpoint, "frames": self.frames,
                "request": self.request.model_dump()}

    def set_scan(self, *, dwell_ns: float | None = None, magnification: float | None = None,
                 working_distance_um: float | None = None) -> dict:
        """Scan the frames that follow with this dwell, magnification or focus (the
        working distance's offset from the nominal one, um, larger deeper)."""
        changes = {key: value for key, value in (("dwell_ns", dwell_ns), ("magnification", magnification),
                                                 ("working_distance_um", working_distance_um)) if value is not None}
        self.request = ScanRequest.model_validate({**self.request.model_dump(), **changes})
        self.typical_scan_s = None  # another dwell: another scan time
        return {key: getattr(self.request, key) for key in ("dwell_ns", "magnification", "working_distance_um")}

    def set_focus_offset(self, working_distance_um: float) -> dict:
        """Focus the frames that follow ``working_distance_um`` from the nominal focus."""
        return self.set_scan(working_distance_um=working_distance_um)

    def close(self) -> None:
        self.client.close()
        if getattr(self, "_sweep_client", None) is not None:
            self._sweep_client.close()


def adapter_source(spec: str, options: dict, fps: float, notify: Callable[[], None] | None = None):
    """A lab's image source (:class:`semservo.instruments.ImageSourceAdapter`), named
    by an entry point of ``semservo.image_sources`` or ``package.module:ClassName`` and
    made with ``options``; a blocking one runs in a background thread."""
    cls = load_plugin(spec, IMAGE_SOURCE_GROUP)
    if not (isinstance(cls, type) and callable(getattr(cls, "acquire", None))):
        raise TypeError(f"{spec!r} is not an image source class (it needs acquire and describe)")
    source = cls(**options)
    for method in ("acquire", "describe"):
        if not callable(getattr(source, method, None)):
            raise TypeError(f"{spec!r} has no {method}(): see semservo.instruments.ImageSource")
    blocking = getattr(source, "blocking", True)
    return BackgroundAcquisition(source, fps=fps, notify=notify) if blocking else source


def _inner(source):
    """The source a background acquisition runs (or the source itself)."""
    return getattr(source, "inner", source)


def _nominal_working_distance(source, target) -> float:
    try:
        return float(target.working_distance())
    except NotSupported:
        last = getattr(source, "last_image", None)
        if last is None or last.working_distance_mm is None:
            raise NotSupported(f"the {source.name} source does not say its working distance (neither "
                               "working_distance() nor its frames): a focus sweep has no centre") from None
        return float(last.working_distance_mm)


@contextlib.contextmanager
def focus_session(source) -> Iterator[Callable[[float], AcquiredImage]]:
    """Scan frames at focus offsets (um from the working distance now, larger deeper) on
    any source that can focus (``"focus" in capabilities(source)``): yields the scan
    function, ``scan(offset_um) -> AcquiredImage``. A source that scans one thing at a
    time (a lab's adapter: one beam) has its stream paused for the sweep and its focus
    set back afterwards; one that can scan beside the stream (``focus_beside_stream``:
    the simulated SEM) scans the sweep meanwhile. Raises :class:`NotSupported` for a
    source that cannot focus."""
    found = capabilities(source)
    if "focus" not in found:
        raise NotSupported(f"the {source.name} source cannot focus, so it cannot sweep the focus (the tilts are "
                           "measured from focus sweeps)")
    target = _inner(source)
    if "focus_beside_stream" in found:
        yield lambda offset_um: target.scan_at_focus(offset_um, None)
        return
    with getattr(source, "instrument", contextlib.nullcontext()):
        nominal = _nominal_working_distance(source, target)
        try:
            yield lambda offset_um: target.scan_at_focus(offset_um, nominal)
        finally:
            target.set_working_distance(nominal)


def set_scan(source, *, dwell_ns: float | None = None, magnification: float | None = None,
             working_distance_mm: float | None = None, working_distance_um: float | None = None) -> dict:
    """Change the scan settings (and the focus) of the frames that follow, on a source
    that can: ``scan_settings`` (dwell, magnification), ``focus`` (the working distance,
    mm), ``focus_offset`` (the simulated SEM's offset from its nominal focus, um).
    Raises :class:`~semservo.instruments.NotSupported` saying what the source cannot do."""
    found, target = capabilities(source), _inner(source)
    result: dict = {}
    if dwell_ns is not None or magnification is not None:
        if "scan_settings" not in found:
            raise NotSupported(f"the {source.name} source cannot change its scan settings")
        result.update(target.set_scan(dwell_ns=dwell_ns, magnification=magnification))
    if working_distance_um is not None:
        if "focus_offset" not in found:
            raise NotSupported(f"working_distance_um is the simulated SEM's focus offset; the {source.name} source "
                               "takes working_distance_mm")
        result.update(target.set_focus_offset(working_distance_um))
    if working_distance_mm is not None:
        if "focus" not in found or "focus_offset" in found:
            raise NotSupported(f"the {source.name} source cannot set the focus"
                               + (" in mm (it takes working_distance_um)" if "focus_offset" in found else ""))
        result["working_distance_mm"] = target.set_working_distance(working_distance_mm)
    return result
