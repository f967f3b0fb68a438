"""The controller's core: motion estimates in, stage moves out, one run at a time.

No sockets here: the stage service (every axis, the rotation stage too) and the
estimator are reached through ports (:class:`semservo.protocol.Port`: typed calls that
raise :class:`~semservo.errors.CommandError` or
:class:`~semservo.errors.ServiceUnavailable`), so the same core runs behind ZeroMQ in
the service and in-process in tests (:class:`semservo.protocol.LocalPort`). The loop's
steps are the pure functions of :mod:`services.controller.run`; the law is
:class:`semservo.control.ControlLaw` (eq. 30-37).

A run is a small state machine::

    idle --start--> servoing --(mean error of the last N fresh frames under tolerance)--> converged
                       |  \\--(diverging, iteration limit, no progress, scene lost, stage refused
                       |      or held, reference changed, no estimate for estimate_timeout_s)--> failed
                       \\--stop--> stopped

A run that can no longer make progress ends as ``failed`` with the reason within a few
seconds; it never waits in ``servoing`` for estimates that will not come, nor goes on
for ever when its error stops falling. A controller killed mid-run leaves its journal
(``runs/<id>.jsonl``, a header line then one line per iteration); the next controller
to start finishes that run as ``failed`` from it, with the stage's command log
(:meth:`ControllerCore.recover`).
"""

from __future__ import annotations

import json
import logging
import math
import re
import time
import uuid
from collections import deque
from pathlib import Path
from typing import Callable

import numpy as np

from semservo.control import (
    MODEL_UNCERTAINTY, AdaptiveGain, CameraToStage, ControlLaw, ExponentialGain, PositionLaw, make_law, make_tilt_law,
    move_pieces,
)
from semservo.errors import BadRequest, CommandError, ServiceUnavailable
from semservo.messages import MotionEstimate
from semservo.protocol import Port
from semservo.protocol import estimator as estimator_protocol
from semservo.protocol import stage as stage_protocol
from semservo.protocol.controller import ControllerState, ControllerStatus, RunSettings
from services.controller.run import (
    IterationRecord, Run, Tilts, Verdict, admit, decide, foreshortening_changed, gate, judge, law_step, measure,
    sampling_time, tilt_step, uses_partial_frames,
)
from services.controller.split import BEAM_AXIS, BeamAxes, split

log = logging.getLogger("controller")

__all__ = ["ControllerCore", "RunSettings", "model_uncertainty"]


def model_uncertainty(stage_state, dofs) -> float:
    """How uncertain the stage's response to a commanded micrometre is, for the position
    law's prior (:data:`semservo.control.MODEL_UNCERTAINTY`): a calibrated
    displacement-voltage model (branches, from ``semservo calibrate``) or a driver in
    physical units answers within 15 %; a linear model from the nominal stroke within 70 %."""
    if stage_state.kind == "physical":
        return MODEL_UNCERTAINTY["calibrated"]
    planar = [axis for axis in ("x", "y") if axis in dofs]
    kinds = {stage_state.models.get(axis, "linear") for axis in planar}
    return MODEL_UNCERTAINTY["calibrated" if kinds and kinds <= {"branches"} else "uncalibrated"]

#: The planar DOF a beam axis moves the content along (the stage's own axes are theirs).
PLANAR_AXIS = {beam: axis for axis, beam in BEAM_AXIS.items()}

#: The stage's axis for each turning DOF.
TURN_AXES = {"rotation": "rotation_deg", "alpha": "tilt_x_deg", "beta": "tilt_y_deg"}

_RUN_ID = re.compile(r"[0-9]{8}-[0-9]{6}-[0-9a-f]{6}")

#: The longest a chained move's next command waits for the stage (its settling and rate
#: limit take milliseconds); where a stage asks for longer, the rest of the move is left
#: to the next fresh frame rather than starve the stage's watchdog of heartbeats.
CHAIN_WAIT_MAX_S = 0.5
#: Between the end of one tick or estimate's handling and the next tick, the service loop
#: polls at most 0.2 s; a gap this long means the process itself did not run (paused,
#: swapped out), and the silence of the estimates in it is not theirs
#: (:meth:`ControllerCore.tick`). A pause longer than the stage's watchdog (3 s) finds
#: the stage held, and the run fails saying so.
STALLED_AFTER_S = 2.0


def _wait_until_ns(when_ns: int) -> bool:
    """Wait until Unix time ``when_ns``; False, at once, when that is more than
    :data:`CHAIN_WAIT_MAX_S` away."""
    delay_s = (when_ns - time.time_ns()) / 1e9
    if delay_s > CHAIN_WAIT_MAX_S:
        return False
    if delay_s > 0:
        time.sleep(delay_s)
    return True


class ControllerCore:
    def __init__(self, stage: Port, *, estimator: Port | None = None, camera: CameraToStage | None = None,
                 runs_dir: Path | None = None, watchdog_s: float = 3.0, name: str = "controller",
                 clock: Callable[[], float] = time.monotonic, publish: Callable[[str, dict], None] | None = None,
                 estimator_at_start: Port | None = None):
        self.stage = stage
        self.estimator = estimator
        #: The estimator as a run's start asks it what to measure: more patient than
        #: ``estimator``, whose timeouts are the running loop's.
        self.estimator_at_start = estimator_at_start or estimator
        self.camera = camera or CameraToStage()
        self.runs_dir = runs_dir
        self.watchdog_s = watchdog_s
        self.owner = f"{name}-{uuid.uuid4().hex[:6]}"
        self.clock = clock
        self.publish = publish or (lambda kind, data: None)
        self.state: ControllerState = "idle"
        self.reason = ""
        self.run: Run | None = None
        self.last_heartbeat = 0.0
        self.last_estimate_at = 0.0  # clock time of the last estimate against the run's reference
        self._ticked_at: float | None = None  # clock time of the last tick while servoing
        self._journal = None

    @property
    def settings(self) -> RunSettings:
        return self.run.settings if self.run is not None else RunSettings()

    # -- run lifecycle -----------------------------------------------------------------
    def start(self, settings: RunSettings, reference: dict | str) -> dict:
        """Start a run towards ``reference`` (the estimator's report of it, or its id).
        A DOF the instrument cannot measure or move is refused here, with the reason
        (:class:`~semservo.errors.BadRequest`), before anything is armed."""
        if self.state == "servoing":
            raise CommandError("busy", f"run {self.run.id} is active; stop it first")
        reference = {"id": reference} if isinstance(reference, str) else reference
        # RunSettings lets each name once; gamma and rotation together name one DOF.
        dofs = list(dict.fromkeys("rotation" if dof == "gamma" else dof for dof in settings.dofs))
        settings = settings.model_copy(update={"dofs": dofs})
        self._check_measurable(dofs, reference)
        self._check_movable(dofs)
        if settings.beam_shift_within_um > 0 and BeamAxes.of(self.stage.call(stage_protocol.STATE)) is None:
            # A valid request this instrument cannot do (409: the system's state says no).
            raise CommandError("no_beam_shift", "beam_shift_within_um needs a beam shift beside the stage (axes "
                                                "beam_x and beam_y of a driver in physical units, such as openfibsem); "
                                                "this stage has none: leave it at 0")
        tilt_dofs = tuple(dof for dof in dofs if dof in ("alpha", "beta"))
        self._estimator_measures(rotation="rotation" in dofs, tilts=bool(tilt_dofs) or None,
                                 required="rotation" in dofs or bool(tilt_dofs), at_start=True)
        try:
            stage_state = self.stage.call(stage_protocol.ARM, hold_after_s=self.watchdog_s, owner=self.owner)
        except CommandError as refusal:
            self._estimator_measures(rotation=None, tilts=None)
            # Named as the stage's here, where it is the stage that said no; every other
            # refusal of a start (the request, the reference, the instrument) keeps its code.
            raise CommandError(f"stage_{refusal.code}", f"the stage refused to start a run: {refusal.message}") \
                from None
        except ServiceUnavailable:
            self._estimator_measures(rotation=None, tilts=None)
            raise
        gain = (ExponentialGain(settings.gain_max, settings.gain_min) if settings.gain == "exponential"
                else AdaptiveGain(settings.gain_scale, settings.gain_min, settings.gain_max))
        planar = tuple(dof for dof in dofs if dof in ("x", "y", "rotation"))
        now_ns = time.time_ns()
        self.run = Run(
            id=time.strftime("%Y%m%d-%H%M%S-") + uuid.uuid4().hex[:6], reference_id=reference["id"],
            settings=settings, started_at_ns=now_ns, stage_at_start=stage_state.model_dump(mode="json"),
            law=make_law(settings.law, planar, camera_to_stage=self.camera, gain=gain,
                         integral_time_s=settings.integral_time_s,
                         model_uncertainty=model_uncertainty(stage_state, planar),
                         tolerance_px=settings.tolerance_px, tolerance_deg=settings.tolerance_deg,
                         max_move_um=settings.max_move_um, max_moves=settings.moves_per_frame,
                         max_turn_deg=settings.max_turn_deg,
                         # A driver in physical units closes its own loop: no creep to follow.
                         creep_per_decade=0.0 if stage_state.kind == "physical" else PositionLaw.creep_per_decade,
                         partial_frames=uses_partial_frames(settings)),
            tilts=Tilts(make_tilt_law(settings.law, tilt_dofs, camera_to_stage=self.camera, gain=gain), settled_ns=now_ns)
            if tilt_dofs else None,
            last_command_ns=now_ns, recent=deque(),
            beam=BeamAxes.of(stage_state) if settings.beam_shift_within_um > 0 else None)
        self.state, self.reason = "servoing", ""
        self.last_heartbeat = self.last_estimate_at = self.clock()
        self._open_journal()
        self._status()
        log.info("run %s started (reference %s, dofs %s)", self.run.id, self.run.reference_id, dofs)
        return self.status()

    def _check_measurable(self, dofs: list[str], reference: dict) -> None:
        """Refuse, up front and in words, a DOF the reference or the frames cannot measure
        (what the estimator said of its reference; absent fields are not held against it)."""
        if any(dof in dofs for dof in ("x", "y")) and "pixel_size_nm" in reference \
                and reference["pixel_size_nm"] is None:
            raise BadRequest("x and y cannot be servoed: the reference's frames carry no pixel size (their files or "
                             "source do not say): set SEMSERVO_IMAGESERVER__PIXEL_SIZE_NM (or the magnification) and "
                             "teach again")
        if "rotation" in dofs and reference.get("kind") == "mask":
            raise BadRequest("rotation cannot be servoed against a mask reference: a mask is matched on its outline, "
                             "without rotation; teach an image, or leave rotation out of dofs")

    def _check_movable(self, dofs: list[str]) -> None:
        turning = [dof for dof in dofs if dof in TURN_AXES]
        if not turning:
            return
        rotation_stage = self.stage.call(stage_protocol.STATE).rotation
        if rotation_stage is None:
            raise BadRequest(f"{', '.join(turning)} cannot be servoed here: the stage service has no "
                             "rotation-and-tilt stage (SEMSERVO_STAGE__ROTATION_STAGE)")
        missing = [dof for dof in turning if TURN_AXES[dof] not in rotation_stage.travel_deg]
        if missing and rotation_stage.travel_deg:
            raise BadRequest(f"the rotation-and-tilt stage has no axis for {', '.join(missing)}")

    def stop(self, reason: str = "stop requested") -> dict:
        """Stop at once: the stage is told to stop first (it refuses further moves until
        resumed), then the run ends as ``stopped``."""
        stage_reachable = True
        try:
            self.stage.call(stage_protocol.STOP, reason=reason)
        except (CommandError, ServiceUnavailable) as error:
            log.error("could not tell the stage to stop: %s", error)
            # A stage that did not answer the stop is not asked for its log as well:
            # that would only delay the run's end (and a stopping controller's exit).
            stage_reachable = not isinstance(error, ServiceUnavailable)
        if self.state == "servoing":
            self._finish("stopped", reason, stage_reachable=stage_reachable)
        return self.status()

    def _estimator_measures(self, rotation: bool | None, tilts: bool | None = None, required: bool = False,
                            at_start: bool = False) -> None:
        """Tell the estimator whether rotation matters (a run without the rotation DOF
        does not need it, and translation alone is three times faster) and whether to
        measure the tilts; None restores its configuration. Not being heard is logged,
        never fatal, unless ``required`` (a run with rotation or the tilts cannot go on
        without what the estimator measures for them). ``at_start``: a run's start
        asks through ``estimator_at_start``, which may wait longer for an estimator still
        busy with a teach (:func:`services.controller.main.estimator_ports`); the running
        loop and a run's end, when the estimator may be dead, cannot."""
        if self.estimator is None:
            if required and tilts:
                raise BadRequest("tilts need the estimator's focus sweeps, and there is no estimator port")
            return
        port = self.estimator_at_start if at_start else self.estimator
        try:
            port.call(estimator_protocol.MEASURE, rotation=rotation, tilts=tilts)
        except (CommandError, ServiceUnavailable) as error:
            if required:
                what = "tilts" if tilts else "rotation"
                if isinstance(error, CommandError):
                    # The estimator's code kept: "no_tilt_reference" is the system's state
                    # (teach with tilts first, HTTP 409), not a malformed request.
                    raise CommandError(error.code, f"{what} cannot be servoed: {error.message}") from None
                raise BadRequest(f"{what} cannot be servoed: the estimator, which measures it, did not take the "
                                 f"request ({error})") from None
            log.warning("could not set the estimator's measurements: %s", error)

    def _estimator_tilted(self, settles_at_ns: int | None) -> bool:
        """Tell the estimator of a tilt move: the focus sweep it is scanning shows poses in
        between (the run would not act on it), so it starts the next once the tilt has
        settled. Whether it did; not being heard costs only time (that sweep is then
        scanned to its end and held as stale)."""
        if self.estimator is None:
            return False
        try:
            return self.estimator.call(estimator_protocol.TILTED, settles_at_ns=settles_at_ns).restarted
        except (CommandError, ServiceUnavailable) as error:
            log.warning("could not tell the estimator of the tilt move: %s", error)
            return False

    def _estimator_moved(self, run: Run, settles_at_ns: int | None) -> None:
        """Tell the estimator when the move settles, for a run that acts on partial frames:
        the frame scanning then is measured on its rows after it. Not being heard costs
        only time (that frame is then measured whole, stale, and the next one is used)."""
        if self.estimator is None or not settles_at_ns or not uses_partial_frames(run.settings):
            return
        try:
            self.estimator.call(estimator_protocol.MOVED, settles_at_ns=settles_at_ns)
        except (CommandError, ServiceUnavailable) as error:
            log.warning("could not tell the estimator of the move: %s", error)

    def _estimator_account(self) -> str:
        """Why estimates stopped, in words, from what the estimator says of itself."""
        if self.estimator is None:
            return "no estimator port to ask"
        try:
            report = self.estimator.call(estimator_protocol.REPORT)
        except ServiceUnavailable as error:
            return f"the estimator does not answer ({error})"
        except CommandError as error:
            return f"the estimator refused a report ({error.message})"
        if report.reference is None:
            return "the estimator has no reference (restarted, or cleared)"
        if report.reference.id != self.run.reference_id:
            return f"the estimator now has reference {report.reference.id} (taught again, or restarted)"
        last = report.last_estimate or {}
        if report.latest_frame_seq is not None and report.latest_frame_seq == last.get("seq"):
            # Its newest frame is one it has already estimated: no frame has reached it since.
            return (f"frames stopped: no frame has reached the estimator since frame {report.latest_frame_seq} (is "
                    f"the image server reachable? semservo health imageserver)")
        return "the estimator has the reference but publishes nothing (are frames arriving?)"

    def _finish(self, state: ControllerState, reason: str, *, recovered: bool = False,
                stage_reachable: bool = True) -> None:
        self.state, self.reason = state, reason
        run = self.run
        if not recovered:  # a recovered run's owner is dead: its watchdog has held the stage
            self._estimator_measures(rotation=None, tilts=None)
            try:
                if state != "stopped" and stage_reachable:  # a finished run releases the watchdog
                    self.stage.call(stage_protocol.DISARM, owner=self.owner)
            except (CommandError, ServiceUnavailable) as error:
                log.warning("disarming the stage watchdog failed: %s", error)
        finished_ns = time.time_ns()
        run.outcome = {"state": state, "reason": reason, "finished_at_ns": finished_ns,
                       "iterations": run.iterations, "fresh_frames": run.fresh_frames,
                       "partial_frames": run.partial_frames,
                       **_time_to_target(run, state, finished_ns), **({"recovered": True} if recovered else {})}
        run.stage_log = []
        if not stage_reachable:  # asking a dead stage again only delays the end (the gateway asks later)
            run.outcome["stage_log_error"] = "the stage service was unreachable when the run ended"
        else:
            try:
                entries = self.stage.call(stage_protocol.LOG, since_ns=run.started_at_ns).entries
                run.stage_log = [entry.model_dump() for entry in entries]
            except (CommandError, ServiceUnavailable) as error:
                run.outcome["stage_log_error"] = str(error)
        self._write_summary()
        log.info("run %s %s: %s after %d iterations", run.id, state, reason, run.iterations)
        self._status()

    def _end(self, verdict: Verdict) -> None:
        if verdict.ending is not None:
            self._finish(verdict.ending, verdict.reason)

    # -- the loop ----------------------------------------------------------------------
    def on_estimate(self, estimate: MotionEstimate) -> dict | None:
        """One estimate in; the iteration record out (None when no run is active, or the
        estimate was not against the run's reference)."""
        try:
            return self._on_estimate(estimate)
        finally:
            self._alive()

    def _alive(self) -> None:
        """This process has just been running: the stall clock of :meth:`tick` starts here
        (after any blocking call of its own, which is not a pause)."""
        self._ticked_at = self.clock() if self.state == "servoing" else None

    def _on_estimate(self, estimate: MotionEstimate) -> dict | None:
        run = self.run
        if self.state != "servoing" or run is None:
            return None
        foreign = admit(run, estimate)
        if foreign is not None:
            self._end(foreign)
            return None
        self.last_estimate_at = self.clock()
        record = IterationRecord.of(estimate)
        held = gate(run, estimate)
        if held is not None:
            self._record(record, held.action)
            self._end(held)
            return record.to_json()
        record.error_px = math.hypot(estimate.dx_px, estimate.dy_px)
        sweeps_before = run.tilts.sweeps if run.tilts is not None else 0
        tilt = tilt_step(run, estimate, record) if run.tilts is not None else None
        elapsed = sampling_time(run, estimate)
        if foreshortening_changed(run, estimate):
            # The turn is read through another foreshortening from here: re-measured.
            run.law.view_moved()
        step = law_step(run, estimate, elapsed, time.time_ns())
        if isinstance(step, Verdict):
            self._record(record, step.action)
            self._end(step)
            return record.to_json()
        measurement = measure(run, estimate, new_sweep=run.tilts is not None and run.tilts.sweeps > sweeps_before)
        record.mean_error_px = measurement.mean_error_px
        verdict = judge(run, measurement)
        if verdict is not None:
            if verdict.action is not None:
                self._record(record, verdict.action)
            self._end(verdict)
            return record.to_json()
        decision = decide(run, step, tilt)
        record.error, record.cost, record.gain, record.velocity = step.error, step.cost, step.gain, step.velocity
        record.sampling_time_s, record.move, record.saturated = elapsed, decision.step.move, decision.saturated
        if decision.diverging:
            self._record(record, "held: diverging")
            self._finish("failed", decision.diverging)
            return record.to_json()
        record.saturated = decision.saturated or decision.turn_saturated
        if decision.turns:
            record.turn_deg = decision.turns
        if not decision.targets and not decision.turns:
            # A tilts-only run between two sweeps, or the position law holding: what is
            # left is within its dead band or not yet beyond the estimate's noise.
            self._record(record, "held: waiting for a focus sweep" if not run.law.dofs
                         else step.held or "held: nothing significant to correct")
            return record.to_json()
        if not self._command(run, decision, tilt is not None, record):
            return record.to_json()
        # What the stage carried out, and when: the position law learns the stage's gain
        # from it (the paper's law needs nothing).
        carried = {f"{PLANAR_AXIS.get(axis, axis)}_um": value for axis, value in (record.targets or {}).items()}
        carried.update({axis: value for axis, value in decision.turns.items() if axis == "rotation_deg"})
        # A chained move has landed by its last command.
        last_written_ns = record.pieces_written_at_ns[-1] if record.pieces_written_at_ns else record.command_written_at_ns
        run.law.applied(carried, last_written_ns / 1e9 if last_written_ns else None)
        if decision.turns.keys() & {TURN_AXES["alpha"], TURN_AXES["beta"]}:
            run.law.view_moved()  # the pivot's lever moves the view by design: the position restarts, the drift stays
        run.iterations += 1
        run.last_command_ns = max(record.command_written_at_ns, record.command_settled_at_ns or 0)
        interval = estimate.frame_source_interval_s
        run.last_source_end_s = interval[1] if interval else None
        run.last_acted_acquired_ns = estimate.frame_acquired_at_ns
        self.last_heartbeat = self.clock()
        record.latency_ms = (record.command_written_at_ns - estimate.frame_published_at_ns) / 1e6
        self._record(record, "moved")
        return record.to_json()

    def _command(self, run: Run, decision, tilting: bool, record: IterationRecord) -> bool:
        """Make the decided move through the stage service; False (the run ended, the
        refusal recorded) when the stage refused or did not answer."""
        try:
            if decision.targets:
                # The stage's axes, or the beam's for the last micrometres (services.controller.split).
                error_um = record.error_px * record.pixel_size_nm / 1000 if record.pixel_size_nm else None
                pieces = move_pieces({f"{axis}_um": value for axis, value in decision.targets.items()},
                                     run.settings.max_move_um)
                record.targets, record.pieces_written_at_ns = {}, []
                written = None
                for piece in pieces:
                    # A chained move: the next command once the last has settled and any
                    # step is within the stage's rate limit (the stage's reply says when).
                    if written is not None and not _wait_until_ns(max(written.settled_at_ns or 0,
                                                                      written.ready_at_ns or 0)):
                        break
                    targets = split({axis[:-3]: value for axis, value in piece.items()}, run.beam,
                                    run.settings.beam_shift_within_um, error_um)
                    written = self.stage.call(stage_protocol.MOVE, targets=targets, relative=True, owner=self.owner)
                    if run.beam is not None:
                        run.beam.follow(written.positions_um)
                    for axis, value in targets.items():
                        record.targets[axis] = record.targets.get(axis, 0.0) + value
                    record.pieces_written_at_ns.append(written.written_at_ns)
                    record.pieces = len(record.pieces_written_at_ns)
                    if record.command_written_at_ns is None:
                        record.command_written_at_ns = written.written_at_ns
                    # Where the stage is after each command: a chain refused part way keeps it.
                    record.command_settled_at_ns = written.settled_at_ns
                    record.voltages, record.positions_um = written.voltages, written.positions_um
            if decision.turns:
                turned = self.stage.call(stage_protocol.ROTATE, targets=decision.turns, relative=True,
                                         owner=self.owner)
                if record.command_written_at_ns is None:
                    record.command_written_at_ns = turned.written_at_ns
                record.angles_deg = turned.angles_deg
                # Frames scanned before the turn or tilt has arrived show a pose in between.
                record.command_settled_at_ns = max(record.command_settled_at_ns or 0, turned.settled_at_ns)
                if tilting:
                    run.tilts.moved(record.command_settled_at_ns)
                    record.tilt_sweeps_restarted = self._estimator_tilted(record.command_settled_at_ns)
                    # A tilt about the pivot below the surface shifts the view: the planar
                    # cost jumps by design, so divergence is judged afresh from here.
                    run.min_cost, run.rising = math.inf, 0
        except CommandError as refusal:
            self._record(record, f"refused by the stage: {refusal.code}")
            if refusal.code == "stopped":
                # An operator's stop reaches the stage first (it must hold at once) and this
                # controller a moment later: a move in between is refused, and the run was
                # stopped, not failed. With the stop's own reason, as when the stop reaches
                # this controller first: the record must not depend on which came first.
                # A stop of the stage's own (outputs it did not command) fails the run, as
                # the heartbeat below finds it.
                if refusal.extra.get("stopped_by") == "stage":
                    self._finish("failed", f"the stage stopped itself: {refusal.extra.get('reason')}")
                else:
                    self._finish("stopped", refusal.extra.get("reason") or f"the stage was stopped: {refusal.message}")
            else:
                self._finish("failed", f"the stage refused the move ({refusal.code}): {refusal.message}")
            return False
        except ServiceUnavailable as error:
            self._record(record, "stage unreachable")
            self._finish("failed", f"the stage service is unreachable: {error}", stage_reachable=False)
            return False
        self._estimator_moved(run, record.command_settled_at_ns)
        return True

    def tick(self) -> float:
        """Periodic work: keep the stage's watchdog fed while servoing (a dead
        controller stops feeding it, and the stage holds); fail a run whose estimates
        stopped. Returns the seconds until it is due again."""
        try:
            return self._tick()
        finally:
            self._alive()

    def _tick(self) -> float:
        if self.state != "servoing":
            return 0.5
        now = self.clock()
        if self._ticked_at is not None and now - self._ticked_at > STALLED_AFTER_S:
            # This process did not run for that long (paused, swapped out, a suspended
            # VM): the silence is its own, not the estimator's. The stage's watchdog has
            # held the stage meanwhile (the heartbeat below says so); the estimates get a
            # fresh deadline rather than a failure that blames another service.
            log.warning("the controller itself did not run for %.1f s; the estimate deadline starts again",
                        now - self._ticked_at)
            self.last_estimate_at = max(self.last_estimate_at, now)
            self.last_heartbeat = -math.inf  # ask the stage now
        silent = now - self.last_estimate_at
        if silent > self.settings.estimate_timeout_s:
            self._finish("failed", f"no estimate against the run's reference for {silent:.1f} s: "
                                   f"{self._estimator_account()}")
            return 0.5
        if now - self.last_heartbeat >= self.watchdog_s / 3:
            try:
                reply = self.stage.call(stage_protocol.HEARTBEAT, owner=self.owner)
                self.last_heartbeat = now
                if reply.state == "stopped" and reply.stopped_by == "request":
                    # An operator's stop that reached the stage and not this controller
                    # (its request given up while this process was not running). A stop
                    # of the stage's own (outputs it did not command) fails the run below.
                    self._finish("stopped", f"the stage was stopped{': ' + reply.reason if reply.reason else ''}")
                elif reply.state != "ready":
                    self._finish("failed", f"the stage is {reply.state}{': ' + reply.reason if reply.reason else ''}")
            except ServiceUnavailable as error:
                self._finish("failed", f"the stage service is unreachable: {error}", stage_reachable=False)
            except CommandError as error:
                self._finish("failed", f"the stage refused a heartbeat: {error}")
            return 0.5 if self.state != "servoing" else self.watchdog_s / 6
        # Wake for the next heartbeat or the estimate deadline, whichever comes first.
        return max(0.01, min(self.last_heartbeat + self.watchdog_s / 3 - now,
                             self.last_estimate_at + self.settings.estimate_timeout_s - now + 0.01))

    # -- records -----------------------------------------------------------------------
    def _record(self, record: IterationRecord, action: str) -> None:
        record.action = action
        if record.tilt_action == "moved" and action != "moved":
            # The tilt law decided a move (tilt_step) but the iteration ended without one
            # (the run converged on this frame, held, or the stage refused): the record
            # must not say the tilts moved, nor count it as the run's last move.
            record.tilt_action = f"not moved: {action}"
        record.t_ns = time.time_ns()
        record.iteration = self.run.iterations
        data = record.to_json()
        self.run.records.append(data)
        if self._journal is not None:
            self._journal.write(json.dumps(data, default=_jsonable) + "\n")
            self._journal.flush()
        self.publish("iteration", data)

    def _open_journal(self) -> None:
        self._close_journal()
        if self.runs_dir is None:
            return
        self.runs_dir.mkdir(parents=True, exist_ok=True)
        self._journal = open(self.runs_dir / f"{self.run.id}.jsonl", "w", encoding="utf-8")  # noqa: SIM115
        self._journal.write(json.dumps({"header": self.run.header(), "owner": self.owner}, default=_jsonable) + "\n")
        self._journal.flush()

    def _close_journal(self) -> None:
        if self._journal is not None:
            self._journal.close()
            self._journal = None

    def _write_summary(self) -> None:
        self._close_journal()
        if self.runs_dir is None:
            return
        path = self.runs_dir / f"{self.run.id}.json"
        self.run.path = str(path)
        path.write_text(json.dumps(self.record(), default=_jsonable, indent=1))

    def recover(self) -> list[str]:
        """Finish the runs a dead controller left (a journal without its summary) as
        ``failed``, with their iterations and the stage's command log since they began.
        Returns their ids; the last one becomes this controller's last run. A journal
        that cannot be read (an empty or torn first line) is said once, with what to do."""
        if self.runs_dir is None or not self.runs_dir.is_dir():
            return []
        recovered = []
        for journal in sorted(self.runs_dir.glob("*.jsonl")):
            if not _RUN_ID.fullmatch(journal.stem) or journal.with_suffix(".json").exists():
                continue  # not a run's journal (e.g. the stage's command log), or finished
            run = _read_journal(journal, self.camera)
            if run is None:
                log.error("cannot read the run journal %s (its header line is missing or torn): left as it is; "
                          "delete it once you have looked at it", journal)
                continue
            self.run = run
            self._finish("failed", "the controller stopped mid-run (killed or crashed); finished from its journal "
                                   "when the controller started again", recovered=True)
            recovered.append(run.id)
        return recovered

    def stored(self, run_id: str) -> dict | None:
        """A finished run's record by id (the active or last one, or its summary file)."""
        if self.run is not None and self.run.id == run_id:
            return self.record()
        if self.runs_dir is None or not _RUN_ID.fullmatch(run_id):
            return None
        path = self.runs_dir / f"{run_id}.json"
        return json.loads(path.read_text()) if path.is_file() else None

    def record(self) -> dict:
        """The active or last run's full record."""
        return {} if self.run is None else self.run.to_record()

    def status(self) -> dict:
        run = self.run
        records = run.records if run is not None else []
        # The error now: of the last fresh frame (one scanned during a move shows a pose in between).
        last = next((r for r in reversed(records) if "error_px" in r and not r.get("action", "").startswith("held: stale")),
                    None)
        last_moved = next((r for r in reversed(records) if r.get("action") == "moved"), None)
        outcome = (run.outcome or {}) if run is not None else {}
        return ControllerStatus(
            state=self.state, reason=self.reason, run_id=run and run.id, dofs=run.dofs if run else [],
            started_at_ns=run and run.started_at_ns, iteration=run.iterations if run else 0,
            error_px=last and last["error_px"], mean_error_px=last and last.get("mean_error_px"),
            error_um=last and last["pixel_size_nm"] and last["error_px"] * last["pixel_size_nm"] / 1000,
            cost=last and last.get("cost"), rotation_deg=last and last["rotation_deg"],
            alpha_deg=next((r["alpha_deg"] for r in reversed(records) if r.get("alpha_deg") is not None), None),
            beta_deg=next((r["beta_deg"] for r in reversed(records) if r.get("beta_deg") is not None), None),
            tilt_iterations=run.tilts.moves if run and run.tilts else 0,
            last_latency_ms=last_moved and last_moved["latency_ms"], held_stale=run.held_stale if run else 0,
            fresh_frames=run.fresh_frames if run else 0, time_to_target_s=outcome.get("time_to_target_s"),
            path=run and run.path,
        ).model_dump(mode="json")

    def _status(self) -> None:
        self.publish("status", self.status())


def _time_to_target(run: Run, state: str, finished_ns: int) -> dict:
    """How long a converged run took: wall seconds, and on the image source's own clock
    (the simulated lab's time: what the same run takes at the real frame rate)."""
    if state != "converged":
        return {}
    scans = [r["frame_source_interval_s"] for r in run.records if r.get("frame_source_interval_s")]
    source_s = (scans[-1][1] - scans[0][0]) if scans else None
    return {"time_to_target_s": (finished_ns - run.started_at_ns) / 1e9,
            **({"source_time_to_target_s": source_s} if source_s is not None else {})}


def _read_journal(path: Path, camera: CameraToStage) -> Run | None:
    """A run as its journal left it: the header, then every iteration written."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
        header = json.loads(lines[0])["header"]
        settings = RunSettings.model_validate_json(json.dumps(header["settings"]))
    except (OSError, ValueError, KeyError, IndexError, TypeError):
        return None
    records = []
    for line in lines[1:]:
        try:
            records.append(json.loads(line))
        except ValueError:
            break  # the line being written when the process died
    moved = [record for record in records if record.get("action") == "moved"]
    return Run(id=header["id"], reference_id=header["reference_id"], settings=settings,
               started_at_ns=header["started_at_ns"], stage_at_start=header.get("stage_at_start") or {},
               law=ControlLaw(camera_to_stage=camera), iterations=len(moved), records=records,
               min_cost=min((r["cost"] for r in records if r.get("cost") is not None), default=math.inf))


def _jsonable(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON serializable")
