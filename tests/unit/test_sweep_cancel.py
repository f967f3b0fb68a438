"""A tilt move cancels the focus sweep in progress: its frames show poses in between,
which the controller would hold as stale, so the image server stops it after the scan in
progress (``cancel_sweep``) and the estimator's tracker starts the next one once the tilt
has settled (``tilted``). Real threads, the image server's sweeps and the estimator's
tracker; the control socket between them replaced by direct calls."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from semservo.errors import CommandError
from semservo.instruments import AcquiredImage
from services.estimator.tilts import TiltTracker
from services.imageserver.sweep import FocusSweeps
from tests.integration.helpers import wait_for


class GatedScans:
    """A focus session's scan that takes a frame only when let through (``open``), or at
    once after ``free_run``: the test decides where each sweep is."""

    def __init__(self):
        self.scanned: list[float] = []
        self.entered = threading.Semaphore(0)
        self.gate = threading.Semaphore(0)
        self.free_run = threading.Event()

    def __call__(self, working_distance_um: float) -> AcquiredImage:
        self.entered.release()
        while not self.free_run.wait(0.01):
            if self.gate.acquire(blocking=False):
                break
        self.scanned.append(working_distance_um)
        now = time.time_ns()
        return AcquiredImage(pixels=np.zeros((8, 8), np.uint8), acquired_at_ns=now, scan_started_at_ns=now,
                             pixel_size_nm=70.0)


def test_a_cancelled_sweep_stops_after_its_scan_in_progress_and_the_next_may_start():
    scans = GatedScans()
    sweeps = FocusSweeps(scans)
    try:
        started = sweeps.start([-2.0, -1.0, 0.0, 1.0, 2.0])
        assert scans.entered.acquire(timeout=5)  # scanning its first frame
        assert sweeps.cancel(started["sweep_id"])["state"] == "scanning", "the scan in progress is finished"
        with pytest.raises(RuntimeError, match="finishing its last scan"):
            sweeps.start([-1.0, 0.0, 1.0])
        scans.gate.release()
        ended = wait_for(lambda: (r := sweeps.result(started["sweep_id"]))["state"] != "scanning" and r, 5,
                         "the cancelled sweep to end")
        assert ended["state"] == "failed" and "cancelled" in ended["error"]
        assert scans.scanned == [-2.0], "no frame after the one in progress"
        scans.free_run.set()
        following = sweeps.start([-1.0, 0.0, 1.0])
        done = wait_for(lambda: (r := sweeps.result(following["sweep_id"]))["state"] != "scanning" and r, 5,
                        "the next sweep")
        assert done["state"] == "done"
        # Cancelling a sweep that has ended leaves it as it ended; an unknown one is said so.
        assert sweeps.cancel(following["sweep_id"])["state"] == "done"
        assert sweeps.result(following["sweep_id"])["state"] == "done"
        with pytest.raises(KeyError, match="no sweep"):
            sweeps.cancel(started["sweep_id"])
    finally:
        scans.free_run.set()
        sweeps.close()


class ImageServerCalls:
    """The image server's sweep commands, called directly (as its handlers do), each
    call noted with when it was made."""

    def __init__(self, sweeps: FocusSweeps):
        self.sweeps = sweeps
        self.calls: list[tuple[str, int]] = []

    def request(self, name: str, **arguments):
        self.calls.append((name, time.time_ns()))
        try:
            if name == "start_sweep":
                return self.sweeps.start(arguments["working_distances_um"])
            if name == "cancel_sweep":
                return self.sweeps.cancel(arguments["sweep_id"])
            return self.sweeps.result(arguments["sweep_id"])
        except RuntimeError as error:
            raise CommandError("busy", str(error)) from None

    def close(self) -> None:
        """No socket to close: the calls are direct."""

    def named(self, name: str) -> list[int]:
        return [at for called, at in self.calls if called == name]


class Frames:
    """The estimator's frame estimates, one every 20 ms (``core.last_estimate``): the view
    moving by ``step_px`` a frame until ``still_from_ns``, then held."""

    def __init__(self, core, still_from_ns: int, step_px: float = 10.0):
        self.core, self.still_from_ns, self.step_px = core, still_from_ns, step_px
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)

    def run(self) -> None:
        seq, dx = 0, 0.0
        while not self.stop.wait(0.02):
            now = time.time_ns()
            seq += 1
            dx += self.step_px if now < self.still_from_ns else 0.0
            self.core.last_estimate = SimpleNamespace(seq=seq, dx_px=dx, dy_px=0.0, confidence=1.0,
                                                      frame_scan_started_at_ns=now - 20_000_000,
                                                      frame_acquired_at_ns=now)


def test_a_tilt_move_cancels_the_tracking_sweep_and_the_next_waits_for_the_tilt_and_the_view_to_settle(monkeypatch):
    from services.estimator import tilts

    scans = GatedScans()
    sweeps = FocusSweeps(scans)
    server = ImageServerCalls(sweeps)
    measured = []
    core = SimpleNamespace(
        measure_tilts=True, tilt_error=None, last_estimate=None, next_sweep=lambda: [-2.0, -1.0, 0.0, 1.0, 2.0],
        sweep_depths=lambda sweep, distances, pixel_nm, *_: len(sweep), sweep_again=lambda depths, *_: False,
        fine_sweep_after=lambda *_: None,
        tilt_from_sweep=lambda sweep, *_, **kw: measured.append(kw["scan_started_at_ns"]) or {"confidence": 1.0})
    tracker = TiltTracker(core, lambda: server, timeout_s=30)
    settles_at = time.time_ns() + 300_000_000
    # The tilt's pivot shifts the view; x, y take it out until 0.3 s after the tilt settled.
    frames = Frames(core, still_from_ns=settles_at + 300_000_000)
    frames.thread.start()
    tracker.start()
    try:
        tracker.wake()
        assert scans.entered.acquire(timeout=5)  # the first tracking sweep scans its first frame
        assert tracker.tilted(settles_at) is True
        wait_for(lambda: server.named("cancel_sweep"), 5, "the tracker to cancel its sweep")
        scans.gate.release()  # the scan in progress ends; no further frame of that sweep
        wait_for(lambda: len(server.named("start_sweep")) >= 2, 10, "the next sweep")
        first_start, second_start = server.named("start_sweep")[:2]
        assert server.named("cancel_sweep") and first_start < server.named("cancel_sweep")[0] < second_start
        assert second_start >= frames.still_from_ns, "the next sweep starts once the tilt and the view have settled"
        assert scans.scanned == [-2.0], "the cancelled sweep scanned no frame after the tilt move"
        assert measured == [] and core.tilt_error is None, "a cancelled sweep is neither reported nor an error"
        # The sweep after the tilt runs to its end and is measured.
        scans.free_run.set()
        wait_for(lambda: measured, 10, "the sweep after the tilt measured")
        assert measured[0] >= settles_at
        # A tilt said to arrive in the far future (a clock out of step, a bad request)
        # holds the next sweep up for a bounded time only.
        monkeypatch.setattr(tilts, "MAX_TILT_WAIT_S", 0.3)
        starts = len(server.named("start_sweep"))
        assert tracker.tilted(2**63 - 1) is True
        wait_for(lambda: len(server.named("start_sweep")) > starts, 10, "the sweep after a tilt far in the future")
        # Not measuring the tilts (a run without them, or teaching): nothing to restart.
        core.measure_tilts = False
        assert tracker.tilted() is False
    finally:
        scans.free_run.set()
        frames.stop.set()
        tracker.stop()
        sweeps.close()


def test_a_view_that_keeps_moving_holds_the_next_sweep_up_for_a_few_frames_only(monkeypatch):
    from services.estimator import tilts

    monkeypatch.setattr(tilts, "STILL_WAIT_S", 600.0)  # only the frames' bound ends the wait
    core = SimpleNamespace(measure_tilts=True, last_estimate=None)
    tracker = TiltTracker(core, lambda: None)
    frames = Frames(core, still_from_ns=time.time_ns() + 10**12)  # never still
    frames.thread.start()
    try:
        wait_for(lambda: core.last_estimate, 5, "frames")
        first = core.last_estimate.seq
        assert tracker._wait_for_still_view(time.time_ns(), lambda: False) is False
        assert core.last_estimate.seq - first >= tilts.STILL_WAIT_FRAMES
        frames.step_px = 0.0
        assert tracker._wait_for_still_view(time.time_ns(), lambda: False) is True
    finally:
        frames.stop.set()


def test_a_teach_says_its_wide_sweeps_then_its_fine_ones_counted_after_them():
    """The tracker's teach state through wide sweeps pooled, the switch to fine sweeps and
    fine sweeps pooled, to the end: ``fine`` and ``wide_sweeps`` say which kind is scanning
    and after how many wide ones, ``sweep`` and ``max_sweeps`` count both (a pooled wide
    sweep once failed the teach on a missing key)."""
    scans = GatedScans()
    scans.free_run.set()
    sweeps = FocusSweeps(scans)
    server = ImageServerCalls(sweeps)
    seen = []
    wide = SimpleNamespace(estimate=SimpleNamespace(alpha_uncertainty_deg=0.12, beta_uncertainty_deg=0.11, sweeps=1))
    switched = SimpleNamespace(estimate=None, fine_sweep=(-1.0, -0.5, 0.0, 0.5, 1.0),
                               wide={"sweeps": 2, "alpha_uncertainty_deg": 0.09, "beta_uncertainty_deg": 0.08})
    fine = SimpleNamespace(estimate=SimpleNamespace(alpha_uncertainty_deg=0.06, beta_uncertainty_deg=0.07, sweeps=1))
    pools = [wide, switched, fine]
    taught = {"tilt": {"sweeps": 2, "alpha_uncertainty_deg": 0.05, "beta_uncertainty_deg": 0.05}}

    def teach_tilt(*_, **__):
        seen.append(dict(core.tilt_teach))
        if pools:
            core.teach_pool = pools.pop(0)
            return None
        return taught

    core = SimpleNamespace(measure_tilts=False, tilt_teach=None, teach_pool=None, teach_tilt=teach_tilt,
                           next_sweep=lambda: [-2.0, -1.0, 0.0, 1.0, 2.0],
                           tilt_settings=SimpleNamespace(teach_sweeps=4, fine_teach_sweeps=8, focus_measure="gradient"))
    tracker = TiltTracker(core, lambda: server, timeout_s=30)
    tracker.teach("r1", 5)
    tracker.start()
    try:
        wait_for(lambda: core.tilt_teach["state"] != "sweeping", 10, "the teach's end")
    finally:
        tracker.stop()
        sweeps.close()
    state = core.tilt_teach
    assert state["state"] == "done", state
    assert [(s["sweep"], s["fine"], s["wide_sweeps"], s["max_sweeps"]) for s in seen] == [
        (1, False, 0, 4), (2, False, 0, 4), (3, True, 2, 10), (4, True, 2, 10)]
    assert seen[2]["pinned_deg"] == [0.09, 0.08] and seen[3]["pinned_deg"] == [0.06, 0.07]
    assert state["pinned_deg"] == [0.05, 0.05] and state["frames"] == 5
