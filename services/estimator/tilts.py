"""Tilts, one focus sweep after another, in a thread of its own (section II-B-2).

A sweep takes seconds of scanning; the estimator keeps measuring every streamed frame
meanwhile. While tilts are measured (``measure {tilts: true}``, set by a run that servoes
them) the tracker asks the image server for a sweep planned from the last one, waits
for it, measures the tilts against the taught sweep, and starts the next. Every motion
estimate carries the latest tilt measurement; the controller acts on each one once.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable

from semservo.transport import CommandError, ControlClient, ServiceUnavailable
from services.imageserver.sweep import decode_sweep

log = logging.getLogger("estimator.tilts")

#: How often a running sweep is asked about.
POLL_S = 0.05


class SweepFailed(RuntimeError):
    """The image server could not sweep (no scanning source, a failed scan, timeout)."""


def run_sweep(client: ControlClient, working_distances_um: list[float], timeout_s: float,
              cancelled: Callable[[], bool] = lambda: False):
    """One focus sweep through the image server: (frames, the sweep's reply)."""
    try:
        started = client.request("start_sweep", working_distances_um=list(working_distances_um))
        deadline = time.monotonic() + timeout_s
        while True:
            if cancelled():
                raise SweepFailed("cancelled")
            reply = client.request("sweep", sweep_id=started["sweep_id"])
            if reply["state"] == "done":
                return decode_sweep(reply), reply
            if reply["state"] == "failed":
                raise SweepFailed(reply.get("error", "the image server's sweep failed"))
            if time.monotonic() > deadline:
                raise SweepFailed(f"no sweep after {timeout_s:g} s ({reply.get('scanned')} of "
                                  f"{reply.get('frames')} frames scanned)")
            time.sleep(POLL_S)
    except (ServiceUnavailable, CommandError) as error:
        raise SweepFailed(f"the image server: {error}") from None


class TiltTracker:
    def __init__(self, core, make_client: Callable[[], ControlClient], *, timeout_s: float = 120.0):
        self.core = core
        self.make_client = make_client
        self.timeout_s = timeout_s
        self.lock = threading.Lock()  # one sweep at a time: a teach's or the tracker's
        self._client: ControlClient | None = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="tilt-tracker", daemon=True)
        self.busy = False

    def client(self) -> ControlClient:
        if self._client is None:
            self._client = self.make_client()
        return self._client

    def start(self) -> None:
        self._thread.start()

    def wake(self) -> None:
        self._wake.set()

    def _run(self) -> None:
        while not self._stop.is_set():
            if not self.core.measure_tilts:
                self._wake.wait(0.5)
                self._wake.clear()
                continue
            try:
                with self.lock:
                    self.busy = True
                    plan = self.core.next_sweep()
                    sweep, reply = run_sweep(self.client(), plan, self.timeout_s,
                                             cancelled=lambda: self._stop.is_set() or not self.core.measure_tilts)
                    if self.core.measure_tilts:
                        result = self.core.tilt_from_sweep(
                            sweep, reply["working_distances_um"], reply["pixel_size_nm"],
                            scan_started_at_ns=reply.get("scan_started_at_ns"),
                            source_interval_s=reply.get("source_interval_s"), took_s=reply.get("took_s"))
                        self.core.tilt_error = None if result["confidence"] > 0 else \
                            f"tilts not measured: {result['reason']}"
            except Exception as error:  # noqa: BLE001 - say why, wait, try again; never die
                if self.core.measure_tilts:
                    self.core.tilt_error = f"tilt measurement failed: {error}"
                    log.warning("%s", self.core.tilt_error)
                self._stop.wait(1.0)
            finally:
                self.busy = False

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=5)
        if self._client is not None:
            self._client.close()
