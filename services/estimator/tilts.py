"""Tilts, one focus sweep after another, in a thread of its own (section II-B-2).

A sweep takes seconds of scanning; the estimator keeps measuring every streamed frame
meanwhile, and its control socket keeps answering. The tracker runs two kinds of job:

* **the taught pose's sweeps**, after a teach with tilts (:meth:`TiltTracker.teach`): the
  teach answers at once, and ``report``'s reference says how far they are
  (``tilt_teach``: sweeping, which sweep of at most how many, scanned of frames, how
  well the sweeps so far pin the tilts; done; or failed with the reason). One sweep
  when it pins the tilts; another of the same view, pooled with the first, while they
  are pinned loosely (up to the settings' ``teach_sweeps``,
  :meth:`~services.estimator.core.EstimatorCore.teach_tilt`);
* **tracking**, while tilts are measured (``measure {tilts: true}``, set by a run that
  servoes them): a sweep planned from the last one, measured against the taught sweep,
  then the next. A sweep that cannot pin the tilts, or pins them loosely near the goal,
  is followed by another of the same plan, their depths pooled, before the tilts are
  reported (:meth:`~services.estimator.core.EstimatorCore.sweep_again`). Every motion
  estimate carries the latest tilt measurement; the controller acts on each one once.
  After each of its tilt moves the controller says so (``tilted``): the sweep in
  progress, whose frames show poses in between, is cancelled on the image server, and
  the next starts once the tilt has settled and the view, which the tilt's pivot
  shifts, has stopped moving (:meth:`TiltTracker.tilted`).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Callable

from semservo.errors import CommandError, ServiceUnavailable
from semservo.transport import ControlClient
from semservo.wording import counted
from services.imageserver.sweep import decode_sweep

log = logging.getLogger("estimator.tilts")

#: How often a running sweep is asked about.
POLL_S = 0.05

#: At most this long (s) a cancelled sweep is waited for to finish the scan it was in.
CANCEL_WAIT_S = 30.0

#: At most this long (s) the next sweep waits for a tilt move to settle (a goniometer
#: settles in well under a second; more would be a clock out of step).
MAX_TILT_WAIT_S = 5.0

#: After a tilt move, the next sweep waits for two consecutive frames whose content is
#: this close (px): the view no longer moved between them (a kernel is 32 px; the last
#: trims of x, y, a pixel or less, change a tenth of its edge or less).
STILL_PX = 1.0
#: ... but for at most this many frames, or this many seconds (a scene that keeps moving,
#: or frames that stopped, does not hold the tilts up for ever).
STILL_WAIT_FRAMES = 8
STILL_WAIT_S = 30.0


class SweepFailed(RuntimeError):
    """The image server could not sweep (no source that can focus, a failed scan, timeout)."""


def run_sweep(client: ControlClient, working_distances_um: list[float], timeout_s: float,
              cancelled: Callable[[], bool] = lambda: False,
              progress: Callable[[int, int], None] = lambda scanned, frames: None,
              stopping: Callable[[], bool] = lambda: False):
    """One focus sweep through the image server: (frames, the sweep's reply).
    ``progress(scanned, frames)`` is told as the scans come in. Once ``cancelled()``,
    the image server is told to stop the sweep and, unless ``stopping()``, waited for
    until it has (the next sweep can then start); SweepFailed("cancelled")."""
    try:
        started = client.request("start_sweep", working_distances_um=list(working_distances_um))
        deadline = time.monotonic() + timeout_s
        while True:
            if cancelled():
                cancel_sweep(client, started["sweep_id"], min(timeout_s, CANCEL_WAIT_S), stopping)
                raise SweepFailed("cancelled")
            reply = client.request("sweep", sweep_id=started["sweep_id"])
            if reply["state"] == "done":
                return decode_sweep(reply), reply
            if reply["state"] == "failed":
                raise SweepFailed(reply.get("error", "the image server's sweep failed"))
            progress(int(reply.get("scanned", 0)), int(reply.get("frames", len(working_distances_um))))
            if time.monotonic() > deadline:
                raise SweepFailed(f"no sweep after {timeout_s:g} s ({reply.get('scanned')} of "
                                  f"{reply.get('frames')} frames scanned)")
            time.sleep(POLL_S)
    except (ServiceUnavailable, CommandError) as error:
        raise SweepFailed(f"the image server: {error}") from None


def cancel_sweep(client: ControlClient, sweep_id: str, wait_s: float,
                 stopping: Callable[[], bool] = lambda: False) -> None:
    """Tell the image server to stop sweep ``sweep_id`` after the scan in progress, and
    wait (at most ``wait_s``, not once ``stopping()``) until it has: the image server
    takes one sweep at a time. Not being heard is logged: the sweep then runs to its
    end, as it did before it could be cancelled."""
    try:
        reply = client.request("cancel_sweep", sweep_id=sweep_id)
        deadline = time.monotonic() + wait_s
        while reply["state"] == "scanning" and time.monotonic() < deadline and not stopping():
            time.sleep(POLL_S)
            reply = client.request("sweep", sweep_id=sweep_id)
    except (ServiceUnavailable, CommandError) as error:
        log.info("could not cancel focus sweep %s: %s", sweep_id, error)


def _spanning(first, last):
    """The source interval from the first sweep's start to the last one's end."""
    if not first or not last:
        return last or first
    return [first[0], last[1]]


class TiltTracker:
    def __init__(self, core, make_client: Callable[[], ControlClient], *, timeout_s: float = 120.0):
        self.core = core
        self.make_client = make_client
        self.timeout_s = timeout_s
        self.lock = threading.Lock()  # one sweep at a time
        self._client: ControlClient | None = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._teach_for: str | None = None  # the reference whose taught-pose sweep is due
        self._thread = threading.Thread(target=self._run, name="tilt-tracker", daemon=True)
        self.busy = False
        # A tilt move (``tilted``): how many so far, and when the last one settles.
        self._tilt_moves = 0
        self._tilt_settles_at_ns = 0
        self._tilt_waited_for = 0  # the tilt moves whose settling the sweeps have waited for

    def client(self) -> ControlClient:
        if self._client is None:
            self._client = self.make_client()
        return self._client

    def start(self) -> None:
        self._thread.start()

    def wake(self) -> None:
        self._wake.set()

    def teach(self, reference_id: str, frames: int) -> dict:
        """Sweep the focus at the taught pose of ``reference_id``, in the background; the
        state (``core.tilt_teach``) says how far it is."""
        self.core.tilt_teach = {"state": "sweeping", "reference_id": reference_id, "scanned": 0, "frames": frames,
                                "error": None, "code": None, "sweep": 1, "fine": False, "wide_sweeps": 0,
                                "max_sweeps": self.core.tilt_settings.teach_sweeps, "pinned_deg": None,
                                "focus_measure": self.core.tilt_settings.focus_measure}
        self._teach_for = reference_id
        self.wake()
        return dict(self.core.tilt_teach)

    def tilted(self, settles_at_ns: int | None = None) -> bool:
        """The sample was tilted (a run's tilt move), arriving at ``settles_at_ns``
        (Unix ns, the stage's clock; None: now): the tracking sweep in progress shows
        poses in between, which the controller would not act on, so it is cancelled and
        the next one starts once the tilt has settled. True if the tilts were being
        measured (tracking, not teaching)."""
        now_ns = time.time_ns()
        # The latest move's arrival, within MAX_TILT_WAIT_S from now: a time far ahead (a
        # clock out of step, a bad request) holds this sweep up that long at most, and
        # not the sweeps after the next move.
        self._tilt_settles_at_ns = min(int(settles_at_ns or now_ns), now_ns + int(MAX_TILT_WAIT_S * 1e9))
        self._tilt_moves += 1
        self.wake()
        return self.core.measure_tilts and self._teach_for is None

    def _wait_for_tilt(self) -> int:
        """Wait until the last tilt move has settled (at most :data:`MAX_TILT_WAIT_S` after
        it was told, in case the stage's clock is not this one) and the view has stopped
        moving after it
        (:meth:`_wait_for_still_view`); the tilt moves so far."""
        while True:
            moves = self._tilt_moves
            if moves == self._tilt_waited_for:
                return moves
            settles_at_ns = self._tilt_settles_at_ns
            wait_s = (settles_at_ns - time.time_ns()) / 1e9
            if wait_s > 0 and self._stop.wait(wait_s):
                return moves
            if moves == self._tilt_moves:
                self._wait_for_still_view(settles_at_ns, lambda: moves != self._tilt_moves)
            if moves == self._tilt_moves or self._stop.is_set():
                self._tilt_waited_for = moves
                return moves

    def _wait_for_still_view(self, after_ns: int, interrupted: Callable[[], bool]) -> bool:
        """Wait until two consecutive frames scanned after ``after_ns`` show the content
        within :data:`STILL_PX` of each other (at most :data:`STILL_WAIT_FRAMES` frames or
        :data:`STILL_WAIT_S`). A tilt about the pivot below the surface shifts the view,
        tens of pixels at a few degrees, and the run's x, y take that out over the next
        frames; a sweep scanned meanwhile would see its kernels' content move between its
        frames (no clear focus peaks: the tilts not measured, and the sweep lost). Whether
        the view was seen still."""
        seen: list[tuple[int, float, float]] = []  # (seq, dx, dy) of the frames since
        deadline = time.monotonic() + STILL_WAIT_S
        while (len(seen) <= STILL_WAIT_FRAMES and time.monotonic() < deadline and self.core.measure_tilts
               and not interrupted() and not self._stop.is_set()):
            estimate = self.core.last_estimate
            if estimate is not None and (not seen or estimate.seq != seen[-1][0]) and estimate.confidence > 0 \
                    and (estimate.frame_scan_started_at_ns or estimate.frame_acquired_at_ns) >= after_ns:
                seen.append((estimate.seq, estimate.dx_px, estimate.dy_px))
                if len(seen) >= 2 and math.hypot(seen[-1][1] - seen[-2][1], seen[-1][2] - seen[-2][2]) <= STILL_PX:
                    return True
            self._stop.wait(POLL_S)
        return False

    def teach_cancel(self) -> None:
        """A reference taught without tilts replaces one whose sweep was still scanning."""
        self._teach_for = None

    def _run(self) -> None:
        while not self._stop.is_set():
            if self._teach_for is None and not self.core.measure_tilts:
                self._wake.wait(0.5)
                self._wake.clear()
                continue
            with self.lock:
                self.busy = True
                try:
                    if self._teach_for is not None:
                        self._teach_sweep(self._teach_for)
                    else:
                        self._track()
                finally:
                    self.busy = False

    def _teach_sweep(self, reference_id: str) -> None:
        core = self.core
        state = core.tilt_teach

        def replaced() -> bool:
            return self._stop.is_set() or self._teach_for != reference_id

        def progress(scanned: int, frames: int) -> None:
            if not replaced():
                state.update(scanned=scanned, frames=frames)

        try:
            while True:
                sweep, reply = run_sweep(self.client(), core.next_sweep(), self.timeout_s, cancelled=replaced,
                                         progress=progress, stopping=self._stop.is_set)
                taught = core.teach_tilt(sweep, reply["working_distances_um"], reply["pixel_size_nm"],
                                         reference_id=reference_id, frame_times_ns=reply.get("frame_times_ns"))
                if taught is not None:
                    break
                pool = core.teach_pool
                if pool.estimate is None:  # the wide sweeps could not pin the tilts: finely from here
                    wide = pool.wide
                    state.update(sweep=state["sweep"] + 1, scanned=0, fine=True, wide_sweeps=wide["sweeps"],
                                 max_sweeps=state["sweep"] + core.tilt_settings.fine_teach_sweeps,
                                 pinned_deg=[wide["alpha_uncertainty_deg"], wide["beta_uncertainty_deg"]])
                    log.info("reference %s: %s pin the tilts to +-%.3f and +-%.3f degree only; sweeping finely "
                             "about the depths they found (%d frames, %.3g um apart)", reference_id,
                             counted(wide["sweeps"], "wide focus sweep"), wide["alpha_uncertainty_deg"],
                             wide["beta_uncertainty_deg"], len(pool.fine_sweep),
                             pool.fine_sweep[1] - pool.fine_sweep[0])
                    continue
                pinned = pool.estimate
                state.update(sweep=state["sweep"] + 1, scanned=0,
                             pinned_deg=[pinned.alpha_uncertainty_deg, pinned.beta_uncertainty_deg])
                kind = "fine focus sweep" if state["fine"] else "focus sweep"
                log.info("reference %s: %s pin the tilts to +-%.3f and +-%.3f degree; sweeping again", reference_id,
                         counted(pinned.sweeps, kind), pinned.alpha_uncertainty_deg, pinned.beta_uncertainty_deg)
            tilt = taught["tilt"]
            state.update(state="done", scanned=len(sweep), frames=len(sweep),
                         pinned_deg=[tilt["alpha_uncertainty_deg"], tilt["beta_uncertainty_deg"]])
            after = f", after {counted(state['wide_sweeps'], 'wide one')}" if state["fine"] else ""
            log.info("taught the tilts of reference %s (%s of %d frames%s: +-%.3f, +-%.3f degree)", reference_id,
                     counted(tilt["sweeps"], "fine sweep" if state["fine"] else "sweep"), len(sweep), after,
                     tilt["alpha_uncertainty_deg"], tilt["beta_uncertainty_deg"])
        except SweepFailed as error:
            state.update(state="failed", code="sweep_failed", error=f"the focus sweep failed: {error}")
        except CommandError as error:  # the sweep cannot tell the tilts, or the reference changed
            state.update(state="failed", code="no_tilt_reference" if error.code != "bad_request" else "replaced",
                         error=error.message)
        except Exception as error:  # noqa: BLE001 - said, and the tracker lives on
            log.exception("the taught pose's sweep failed")
            state.update(state="failed", code="sweep_failed", error=f"{type(error).__name__}: {error}")
        finally:
            if self._teach_for == reference_id:
                self._teach_for = None
        if state["state"] == "failed":
            log.warning("reference %s: %s", reference_id, state["error"])

    def _track(self) -> None:
        core = self.core
        moves = self._wait_for_tilt()

        def tilted_since() -> bool:
            return self._tilt_moves != moves

        try:
            plan = core.next_sweep()
            cancelled = (lambda: self._stop.is_set() or not core.measure_tilts or self._teach_for is not None
                         or tilted_since())
            earlier: list = []  # the same view's sweeps before this one, while they are pooled
            first, took_s, fine = None, 0.0, False
            while True:
                sweep, reply = run_sweep(self.client(), plan, self.timeout_s, cancelled=cancelled,
                                         stopping=self._stop.is_set)
                first = first or reply
                took_s += reply.get("took_s") or 0.0
                if not core.measure_tilts:
                    return
                distances, pixel_nm = reply["working_distances_um"], reply["pixel_size_nm"]
                depths = core.sweep_depths(sweep, distances, pixel_nm, reply.get("frame_times_ns"))
                finer = None if fine else core.fine_sweep_after([*earlier, depths], distances, pixel_nm)
                if finer is not None:
                    # Against a finely taught reference: the view swept as the teach was,
                    # about the depths just found; those sweeps are pooled from here.
                    log.info("the sweeps cannot pin the tilts; sweeping finely (%d frames)", len(finer))
                    plan, earlier, fine = finer, [], True
                    continue
                if not core.sweep_again([*earlier, depths], distances, pixel_nm):
                    break
                earlier.append(depths)
            # Reported as scanned from the first sweep's start: a tilt move during any of
            # them leaves the whole measurement stale (the controller holds it).
            result = core.tilt_from_sweep(
                sweep, distances, pixel_nm, scan_started_at_ns=first.get("scan_started_at_ns"),
                source_interval_s=_spanning(first.get("source_interval_s"), reply.get("source_interval_s")),
                took_s=took_s or None, earlier=earlier, sweep_depth_map=depths)
            core.tilt_error = None if result["confidence"] > 0 else f"tilts not measured: {result['reason']}"
        except SweepFailed as error:
            if tilted_since() and not self._stop.is_set():
                log.info("focus sweep cancelled: the sample was tilted while it scanned")
                return  # the next sweep starts once the tilt has settled
            self._track_failed(error)
        except Exception as error:  # noqa: BLE001 - say why, wait, try again; never die
            self._track_failed(error)

    def _track_failed(self, error: Exception) -> None:
        """Say why (while tilts are measured), wait, and let the loop try again."""
        if self.core.measure_tilts:
            self.core.tilt_error = f"tilt measurement failed: {error}"
            log.warning("%s", self.core.tilt_error)
        self._stop.wait(1.0)

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=5)
        if self._client is not None:
            self._client.close()
