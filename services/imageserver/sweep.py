"""Focus sweeps for the tilt measurement (paper section II-B-2): the same field scanned at
a series of working distances, in a thread of its own, while the frame stream goes on.

A sweep takes several scans; the control socket must stay responsive meanwhile, so a
sweep is started (``start_sweep``), runs in the background, and its frames are fetched
when it is done (``sweep``). One sweep at a time; the last one's result is kept until
the next starts. A sweep whose frames will not be used (the sample was tilted while it
scanned, the run ended) is cancelled (``cancel_sweep``): it stops after the scan in
progress (its state then says ``failed``, "cancelled"), and the next may start. No
sockets here: ``session()`` opens a focus session on the source
(:func:`services.imageserver.sources.focus_session`), whose ``scan(offset_um)``
acquires one frame.
"""

from __future__ import annotations

import base64
import contextlib
import logging
import math
import threading
import time
import uuid
from typing import Callable, ContextManager

import numpy as np

from semservo.instruments import AcquiredImage, scan_middle_ns

log = logging.getLogger("imageserver.sweep")

from semservo.protocol.imageserver import MAX_SWEEP_FRAMES

ScanAt = Callable[[float], AcquiredImage]


def check_working_distances(values) -> list[float]:
    """The sweep's working distances (um offsets): 3 to ``MAX_SWEEP_FRAMES`` finite
    numbers, increasing and evenly spaced; ValueError naming what is wrong."""
    if not isinstance(values, list) or not 3 <= len(values) <= MAX_SWEEP_FRAMES:
        raise ValueError(f"working_distances_um must be a list of 3..{MAX_SWEEP_FRAMES} numbers")
    checked = []
    for value in values:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                or abs(value) > 1e4:
            raise ValueError(f"working_distances_um: {value!r} is not a finite number of micrometres (|x| <= 1e4)")
        checked.append(float(value))
    steps = np.diff(checked)
    if (steps <= 0).any() or np.ptp(steps) > 1e-6 * abs(steps.mean()):
        raise ValueError("working_distances_um must be increasing and evenly spaced")
    return checked


class SweepCancelled(Exception):
    """The sweep was cancelled (``cancel_sweep``, or the server stopping)."""


class FocusSweeps:
    def __init__(self, session: Callable[[], ContextManager[ScanAt]] | ScanAt):
        # A plain scan function is a session of its own (tests, sources without a stream).
        self.session = session if _is_session(session) else (lambda: contextlib.nullcontext(session))
        self._lock = threading.Lock()
        self._state: dict = {}
        self._thread: threading.Thread | None = None
        self._cancel = threading.Event()

    def start(self, working_distances_um) -> dict:
        distances = check_working_distances(working_distances_um)
        with self._lock:
            if self._thread is not None and self._thread.is_alive():
                raise RuntimeError(f"sweep {self._state['sweep_id']} is still "
                                   f"{'finishing its last scan' if self._cancel.is_set() else 'scanning'}")
            self._cancel.clear()
            self._state = {"sweep_id": uuid.uuid4().hex[:10], "state": "scanning", "scanned": 0,
                           "frames": len(distances), "working_distances_um": distances, "started_at": time.monotonic()}
            self._thread = threading.Thread(target=self._run, args=(self._state, distances), name="focus-sweep",
                                            daemon=True)
            self._thread.start()
            return {key: self._state[key] for key in ("sweep_id", "state", "frames", "working_distances_um")}

    def _run(self, state: dict, distances: list[float]) -> None:
        images: list[AcquiredImage] = []
        try:
            with self.session() as scan:
                for distance in distances:
                    if self._cancel.is_set():
                        raise SweepCancelled("cancelled")
                    images.append(scan(distance))
                    state["scanned"] = len(images)
            shapes = {image.pixels.shape for image in images}
            if len(shapes) != 1:
                raise ValueError(f"the sweep's frames differ in size: {sorted(shapes)}")
            first, last = images[0], images[-1]
            result = {
                "state": "done", "dtype": str(first.pixels.dtype), "shape": list(first.pixels.shape),
                "frames_b64": [base64.b64encode(np.ascontiguousarray(image.pixels).tobytes()).decode()
                               for image in images],
                "pixel_size_nm": first.pixel_size_nm, "magnification": first.magnification,
                "scan_started_at_ns": first.scan_started_at_ns or first.acquired_at_ns,
                "acquired_at_ns": last.acquired_at_ns,
                "frame_times_ns": [scan_middle_ns(image.scan_started_at_ns, image.acquired_at_ns) for image in images],
                "source_interval_s": ([first.source_interval_s[0], last.source_interval_s[1]]
                                      if first.source_interval_s and last.source_interval_s else None),
                "took_s": time.monotonic() - state["started_at"],
            }
        except SweepCancelled:
            log.info("focus sweep %s cancelled after %d of %d frames", state["sweep_id"], len(images), len(distances))
            result = {"state": "failed", "error": "cancelled"}
        except Exception as error:  # noqa: BLE001 - a failed sweep says why; the stream goes on
            log.warning("focus sweep %s failed: %s", state["sweep_id"], error)
            result = {"state": "failed", "error": f"{type(error).__name__}: {error}"}
        with self._lock:
            state.update(result)

    def _last(self, sweep_id) -> dict:
        """The state of sweep ``sweep_id`` (hold the lock); KeyError if it is not the last."""
        if not self._state or sweep_id != self._state["sweep_id"]:
            raise KeyError(f"no sweep {sweep_id!r} (the last one was "
                           f"{self._state.get('sweep_id') if self._state else 'none'})")
        return self._state

    def result(self, sweep_id) -> dict:
        """The sweep's state; its frames (base64, raw pixels) once done."""
        with self._lock:
            return {key: value for key, value in self._last(sweep_id).items() if key != "started_at"}

    def cancel(self, sweep_id) -> dict:
        """Stop sweep ``sweep_id`` after the scan in progress (it ends ``failed``,
        "cancelled"); a sweep already ended is left as it is. Returns its state without
        frames; KeyError if it is not the last sweep."""
        with self._lock:
            state = self._last(sweep_id)
            if state["state"] == "scanning":
                self._cancel.set()
            return {key: value for key, value in state.items() if key not in ("started_at", "frames_b64")}

    def close(self) -> None:
        self._cancel.set()
        if self._thread is not None:
            self._thread.join(timeout=5)


def _is_session(function) -> bool:
    """A session factory takes no argument; a scan function takes the focus offset."""
    import inspect

    try:
        return not inspect.signature(function).parameters
    except (TypeError, ValueError):
        return False


def decode_sweep(result: dict) -> np.ndarray:
    """A done sweep's frames as an array (frames, rows, cols)."""
    dtype, shape = np.dtype(result["dtype"]), tuple(result["shape"])
    return np.stack([np.frombuffer(base64.b64decode(data), dtype=dtype).reshape(shape)
                     for data in result["frames_b64"]])
