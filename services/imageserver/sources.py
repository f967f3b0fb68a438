"""Frame sources. A source yields acquired images with their metadata; the image
server core paces, numbers and stamps them.

Every source has the same small interface (:class:`FrameSource`), so a vendor adapter
or the simulated SEM plugs in where ``replay`` sits.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

import zmq

from semservo.config import pixel_size_nm
from semservo.imagefiles import ImageFileError, list_frames, read_image
from semservo.messages import Reply, ScanRequest
from semservo.transport import ControlClient, RequestCancelled, ServiceUnavailable
from semservo.wire import WireError, decode_frame


@dataclass(frozen=True)
class AcquiredImage:
    """One image as a source delivers it."""

    pixels: np.ndarray
    acquired_at_ns: int
    pixel_size_nm: float
    magnification: float
    dwell_ns: float
    label: str | None = None
    scan_started_at_ns: int | None = None  # None: the source does not know (a file)
    source_interval_s: tuple[float, float] | None = None


class FrameSource(Protocol):
    name: str

    def acquire(self) -> AcquiredImage | None:
        """The next image, or None when the source has no more."""

    def describe(self) -> dict: ...


class ReplaySource:
    """Replays a folder of PNG or TIFF frames (8 or 16 bit) in name order.

    Metadata comes from the command line or settings when given (``magnification``,
    ``pixel_size_nm``, ``dwell_ns`` not None), else from each file, else from the
    ``default_*`` values. Every file is read and checked when the source is made, so a
    bad folder fails at start with the file named, not halfway through a run.
    """

    name = "replay"

    def __init__(
        self,
        folder: str | Path,
        *,
        pattern: str = "*",
        loop: bool = True,
        magnification: float | None = None,
        pixel_size_nm: float | None = None,
        dwell_ns: float | None = None,
        default_magnification: float = 1000.0,
        default_dwell_ns: float = 720.0,
    ):
        self.folder = Path(folder)
        self.loop = loop
        self.paths = list_frames(self.folder, pattern)
        if not self.paths:
            raise FileNotFoundError(f"no PNG or TIFF frames matching {pattern!r} in {self.folder}")
        self.images: list[tuple[np.ndarray, dict[str, float]]] = []
        for path in self.paths:
            pixels, metadata = read_image(path)
            pixels.setflags(write=False)  # published zero-copy: nobody may change it
            self.images.append((pixels, metadata))
        first = self.images[0][0]
        for path, (pixels, _) in zip(self.paths, self.images):
            if pixels.shape != first.shape or pixels.dtype != first.dtype:
                raise ImageFileError(
                    f"{path}: {pixels.shape} {pixels.dtype} differs from {self.paths[0].name}'s "
                    f"{first.shape} {first.dtype}; a replay folder holds one kind of frame"
                )
        self.overrides = {
            key: value
            for key, value in (("magnification", magnification), ("pixel_size_nm", pixel_size_nm), ("dwell_ns", dwell_ns))
            if value is not None
        }
        self.defaults = {"magnification": default_magnification, "dwell_ns": default_dwell_ns}
        self.position = 0
        self.passes = 0

    def _metadata(self, from_file: dict[str, float], width: int) -> dict[str, float]:
        merged = {**self.defaults, **from_file, **self.overrides}
        if "pixel_size_nm" not in merged or ("magnification" in self.overrides and "pixel_size_nm" not in self.overrides):
            merged["pixel_size_nm"] = pixel_size_nm(merged["magnification"], width)
        return merged

    def acquire(self) -> AcquiredImage | None:
        if self.position >= len(self.images):
            if not self.loop:
                return None
            self.position = 0
            self.passes += 1
        pixels, from_file = self.images[self.position]
        path = self.paths[self.position]
        self.position += 1
        metadata = self._metadata(from_file, pixels.shape[1])
        return AcquiredImage(pixels=pixels, acquired_at_ns=time.time_ns(), label=path.name, **metadata)

    def describe(self) -> dict:
        pixels = self.images[0][0]
        return {
            "source": self.name,
            "folder": str(self.folder),
            "frames": len(self.paths),
            "shape": list(pixels.shape),
            "dtype": str(pixels.dtype),
            "loop": self.loop,
            "position": self.position,
            "passes": self.passes,
        }


class SourceUnavailable(RuntimeError):
    """The source cannot deliver a frame now (e.g. the fake lab does not answer)."""


class NotReady(Exception):
    """No new frame yet (the scan is still running); not an error, not the end."""


class BackgroundAcquisition:
    """Runs a blocking source (a scan takes a frame time) in a thread of its own, so the
    service's sockets, health above all, stay responsive while a frame is acquired.

    :meth:`acquire` never blocks: it returns the newest frame the thread has, raises
    :class:`NotReady` when there is none yet, and re-raises the thread's last source
    error (once). The thread paces itself at ``fps`` at most.
    """

    def __init__(self, source, fps: float):
        self.source = source
        self.name = source.name
        self.fps = fps
        self._latest: AcquiredImage | None = None
        self._error: Exception | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"acquire-{source.name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        next_due = time.monotonic()
        while not self._stop.is_set():
            wait = next_due - time.monotonic()
            if wait > 0 and self._stop.wait(wait):
                return
            next_due = max(next_due + 1.0 / self.fps, time.monotonic())
            try:
                image = self.source.acquire(cancelled=self._stop.is_set)
            except NotReady:  # cancelled: we are stopping
                return
            except SourceUnavailable as error:
                with self._lock:
                    self._error = error
                self._stop.wait(1.0)
                continue
            with self._lock:
                self._latest, self._error = image, None

    def acquire(self) -> AcquiredImage:
        with self._lock:
            image, error = self._latest, self._error
            self._latest = None
            self._error = None
        if image is not None:
            return image
        if error is not None:
            raise error
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
        started = time.monotonic()
        try:
            parts = self.client.request_parts(self.request.model_dump_json().encode(), timeout_s=self._timeout(),
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
        return AcquiredImage(pixels=frame.pixels, acquired_at_ns=header.acquired_at_ns or header.published_at_ns,
                             pixel_size_nm=header.pixel_size_nm, magnification=header.magnification,
                             dwell_ns=header.dwell_ns, label=header.label,
                             scan_started_at_ns=header.scan_started_at_ns,
                             source_interval_s=header.source_interval_s)

    def describe(self) -> dict:
        return {"source": self.name, "endpoint": self.endpoint, "frames": self.frames,
                "request": self.request.model_dump()}

    def close(self) -> None:
        self.client.close()
