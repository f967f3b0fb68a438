"""The controller's core: motion estimates in, stage moves out, one run at a time.

No sockets here: the stage service (every axis, the rotation stage too) is reached through ports (objects
with ``request(command, args) -> dict`` that raise :class:`CommandError` or
:class:`ServiceUnavailable`), so the same core runs behind ZeroMQ in the service and
in-process in tests. The law itself is :class:`semservo.control.ControlLaw` (eq. 30-37).

A run is a small state machine::

    idle --start--> servoing --(mean error of the last N fresh frames under tolerance)--> converged
                       |  \\--(diverging, iteration limit, scene lost, stage refused or
                       |      held, reference changed, no estimate for estimate_timeout_s)--> failed
                       \\--stop--> stopped

A run that can no longer make progress ends as ``failed`` with the reason within a few
seconds; it never waits in ``servoing`` for estimates that will not come. A controller
killed mid-run leaves its journal (``runs/<id>.jsonl``, a header line then one line per
iteration); the next controller to start finishes that run as ``failed`` from it, with
the stage's command log (:meth:`ControllerCore.recover`).

Only a fresh, confident estimate moves the stage. Fresh: the frame's scan began after
the last move was written (a frame scanned during a move shows a mix of both
positions, and acting on it would count the move twice). Confident: the estimate's
peak confidence is at least ``min_confidence``. Anything else holds the stage, and is
recorded.
"""

from __future__ import annotations

import json
import logging
import math
import re
import time
import uuid
from pathlib import Path
from typing import Annotated, Callable, Literal, Protocol

import numpy as np
from pydantic import BaseModel, BeforeValidator, Field, PositiveFloat, PositiveInt

from semservo.control import AdaptiveGain, CameraToStage, ControlLaw, ExponentialGain, TiltLaw
from semservo.messages import MotionEstimate
from semservo.transport import CommandError, ServiceUnavailable

log = logging.getLogger("controller")

ControllerState = Literal["idle", "servoing", "converged", "failed", "stopped"]


class Port(Protocol):
    def request(self, command: str, args: dict | None = None) -> dict: ...


def _whole(value):
    """A JSON number with no fraction (297.0) is a whole number, as JSON Schema says; 297.5,
    text and booleans stay refused (the model is strict)."""
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return value


#: A count: a positive whole number, given as 3 or 3.0.
Count = Annotated[PositiveInt, BeforeValidator(_whole)]


class RunSettings(BaseModel):
    """What a positioning run may be told; every field has a sane default."""

    model_config = {"extra": "forbid", "allow_inf_nan": False, "strict": True}

    dofs: list[Literal["x", "y", "rotation", "gamma", "alpha", "beta"]] = Field(
        ["x", "y"], min_length=1, max_length=5,
        description="degrees of freedom: x, y, rotation (about the beam; also called gamma), alpha and beta (the "
                    "tilts about the image's x and y axes, measured from focus sweeps)")
    tolerance_px: PositiveFloat = Field(0.1, le=50, description="converged when the translation error is below")
    tolerance_deg: PositiveFloat = Field(0.05, le=10, description="and the rotation error below (rotation DOF)")
    tolerance_tilt_deg: PositiveFloat = Field(0.1, le=10, description="and each tilt error below (alpha, beta DOFs)")
    max_turn_deg: PositiveFloat = Field(5.0, le=30, description="largest turn or tilt per iteration (saturation)")
    min_tilt_confidence: float = Field(0.3, ge=0, le=1, description="less confident tilt measurements hold the tilts")
    converge_frames: Count = Field(3, le=100, description="converged when the mean error of this many fresh frames is under tolerance")
    converge_on: Literal["mean", "each"] = Field(
        "mean", description="'mean': their mean error is under tolerance; 'each': every one of them is too "
                            "(lands nearer, takes more frames, and may never end where vibration exceeds the tolerance)")
    max_iterations: Count = Field(150, le=100_000, description="moves before the run fails")
    gain: Literal["adaptive", "exponential"] = Field("adaptive", description="eq. 35, or the exponential gain")
    gain_scale: PositiveFloat = Field(50.0, description="Lambda of eq. 35 (error x s)")
    gain_min: PositiveFloat = Field(0.5, le=10, description="per second")
    gain_max: PositiveFloat = Field(0.8, le=10, description="per second")
    min_confidence: float = Field(0.5, ge=0, le=1, description="lower-confidence estimates hold the stage")
    lost_after: Count = Field(10, le=1000, description="low-confidence frames in a row: the scene is lost")
    max_move_um: PositiveFloat = Field(10.0, le=100, description="largest stage move per iteration (saturation)")
    integral_time_s: float | None = Field(
        10.0, gt=0, le=1000,
        description="integral action T_i in seconds, against drift (null: the paper's proportional law)")
    hold: bool = Field(False, description="keep servoing after convergence (hold against drift)")
    diverge_factor: float = Field(4.0, gt=1, le=1e6, description="cost above this x its minimum ...")
    diverge_iterations: Count = Field(5, le=1000, description="... for this many moves in a row: diverging")
    diverge_floor_px: PositiveFloat = Field(
        1.0, le=100, description="... never judged on errors under this (estimation noise and vibration near the "
                                 "target are not divergence, however small the tolerance)")
    estimate_timeout_s: PositiveFloat = Field(
        5.0, le=600, description="no estimate against the run's reference for this long (wall clock): the run fails")


class ControllerCore:
    def __init__(self, stage: Port, *, estimator: Port | None = None,
                 camera: CameraToStage | None = None,
                 runs_dir: Path | None = None, watchdog_s: float = 3.0, name: str = "controller",
                 clock: Callable[[], float] = time.monotonic, publish: Callable[[str, dict], None] | None = None):
        self.stage = stage
        self.estimator = estimator
        self.camera = camera or CameraToStage()
        self.runs_dir = runs_dir
        self.watchdog_s = watchdog_s
        self.owner = f"{name}-{uuid.uuid4().hex[:6]}"
        self.clock = clock
        self.publish = publish or (lambda kind, data: None)
        self.state: ControllerState = "idle"
        self.reason = ""
        self.run: dict | None = None
        self.settings = RunSettings()
        self.law = ControlLaw()
        self.tilt_law: TiltLaw | None = None
        self.last_heartbeat = 0.0
        self.last_estimate_at = 0.0  # clock time of the last estimate against the run's reference
        self.foreign_estimates = 0  # estimates in a row against another reference
        self._journal = None

    # -- run lifecycle -----------------------------------------------------------------
    def start(self, settings: RunSettings, reference_id: str) -> dict:
        if self.state == "servoing":
            raise RuntimeError(f"run {self.run['id']} is active")
        dofs = list(dict.fromkeys("rotation" if dof == "gamma" else dof for dof in settings.dofs))
        if len(dofs) != len(settings.dofs):
            raise ValueError(f"dofs: each degree of freedom once (gamma is rotation), got {settings.dofs}")
        settings = settings.model_copy(update={"dofs": dofs})
        turning = [dof for dof in dofs if dof in ("rotation", "alpha", "beta")]
        if turning:
            rotation_stage = self.stage.request("state").get("rotation")
            if rotation_stage is None:
                raise ValueError(f"{', '.join(turning)} cannot be servoed here: the stage service has no "
                                 "rotation-and-tilt stage (SEMSERVO_STAGE__ROTATION_STAGE)")
            axes = {"rotation": "rotation_deg", "alpha": "tilt_x_deg", "beta": "tilt_y_deg"}
            missing = [dof for dof in turning if axes[dof] not in (rotation_stage.get("travel_deg") or {})]
            if missing and rotation_stage.get("travel_deg"):
                raise ValueError(f"the rotation-and-tilt stage has no axis for {', '.join(missing)}")
        tilts = tuple(dof for dof in dofs if dof in ("alpha", "beta"))
        if tilts:
            self._estimator_measures(rotation="rotation" in dofs, tilts=True, required=True)
        stage_state = self.stage.request("arm", {"hold_after_s": self.watchdog_s, "owner": self.owner})
        gain = (ExponentialGain(settings.gain_max, settings.gain_min) if settings.gain == "exponential"
                else AdaptiveGain(settings.gain_scale, settings.gain_min, settings.gain_max))
        planar = tuple(dof for dof in settings.dofs if dof in ("x", "y", "rotation"))
        self.law = ControlLaw(planar, gain, self.camera, integral_time_s=settings.integral_time_s)
        self.tilt_law = TiltLaw(tilts, gain, self.camera.tilt_signs) if tilts else None
        self.settings = settings
        now_ns = time.time_ns()
        self.run = {
            "id": time.strftime("%Y%m%d-%H%M%S-") + uuid.uuid4().hex[:6],
            "reference_id": reference_id, "settings": settings.model_dump(), "started_at_ns": now_ns,
            "stage_at_start": stage_state, "iterations": 0, "records": [], "outcome": None,
            "last_command_ns": now_ns, "last_source_end_s": None, "low_confidence": 0,
            "min_cost": math.inf, "rising": 0, "held_stale": 0, "recent": [],
            # Tilts: the last sweep acted on, when the last tilt move has arrived, the
            # last fresh measurement (None until a sweep after the last tilt move).
            "last_tilt_seq": None, "tilt_settled_ns": now_ns, "tilt_error": None, "last_tilt_end_s": None,
            "tilt_iterations": 0,
        }
        self.state, self.reason = "servoing", ""
        if not tilts:
            self._estimator_measures(rotation="rotation" in settings.dofs)
        self.last_heartbeat = self.last_estimate_at = self.clock()
        self.foreign_estimates = 0
        self._open_journal()
        self._status()
        log.info("run %s started (reference %s, dofs %s)", self.run["id"], reference_id, settings.dofs)
        return self.status()

    def stop(self, reason: str = "stop requested") -> dict:
        """Stop at once: the stage is told to stop first (it refuses further moves until
        resumed), then the run ends as ``stopped``."""
        try:
            self.stage.request("stop", {"reason": reason})
        except (CommandError, ServiceUnavailable) as error:
            log.error("could not tell the stage to stop: %s", error)
        if self.state == "servoing":
            self._finish("stopped", reason)
        return self.status()

    def _estimator_measures(self, rotation: bool | None, tilts: bool | None = None, required: bool = False) -> None:
        """Tell the estimator whether rotation matters (a run without the rotation DOF
        does not need it, and translation alone is three times faster) and whether to
        measure the tilts; None restores its configuration. Not being heard is logged,
        never fatal, unless ``required`` (a tilt run cannot go without its sweeps)."""
        if self.estimator is None:
            if required:
                raise ValueError("tilts need the estimator's focus sweeps, and there is no estimator port")
            return
        try:
            self.estimator.request("measure", {"rotation": rotation, "tilts": tilts})
        except (CommandError, ServiceUnavailable) as error:
            if required:
                if isinstance(error, CommandError) and error.code == "no_tilt_reference":
                    raise ValueError(f"tilts cannot be servoed: {error.message}") from None
                raise ValueError(f"tilts cannot be servoed: the estimator, which measures them, did not take the "
                                 f"request ({error})") from None
            log.warning("could not set the estimator's measurements: %s", error)

    def _estimator_account(self) -> str:
        """Why estimates stopped, in words, from what the estimator says of itself."""
        if self.estimator is None:
            return "no estimator port to ask"
        try:
            report = self.estimator.request("report", {})
        except ServiceUnavailable as error:
            return f"the estimator does not answer ({error})"
        except CommandError as error:
            return f"the estimator refused a report ({error.message})"
        reference = report.get("reference")
        if not reference:
            return "the estimator has no reference (restarted, or cleared)"
        if reference.get("id") != self.run["reference_id"]:
            return f"the estimator now has reference {reference.get('id')} (taught again, or restarted)"
        latest, last = report.get("latest_frame_seq"), report.get("last_estimate") or {}
        if latest is not None and latest == last.get("seq"):  # its newest frame is one it has estimated
            return (f"frames stopped: no frame has reached the estimator since frame {latest} (is the image server "
                    f"reachable? semservo health imageserver)")
        return "the estimator has the reference but publishes nothing (are frames arriving?)"

    def _within(self, dx_px: float, dy_px: float, rotation_deg: float) -> bool:
        """The translation error, the turn when rotation is servoed, and the last fresh
        tilts when they are, under tolerance."""
        dofs = self.settings.dofs
        within = (("x" not in dofs and "y" not in dofs) or math.hypot(dx_px, dy_px) <= self.settings.tolerance_px) \
            and ("rotation" not in dofs or abs(rotation_deg) <= self.settings.tolerance_deg)
        if within and self.tilt_law is not None:
            tilt = self.run.get("tilt_error")
            within = tilt is not None and all(abs(tilt[dof]) <= self.settings.tolerance_tilt_deg
                                              for dof in self.tilt_law.dofs)
        return within

    def _finish(self, state: ControllerState, reason: str, *, recovered: bool = False,
                stage_reachable: bool = True) -> None:
        self.state, self.reason = state, reason
        run = self.run
        if not recovered:  # a recovered run's owner is dead: its watchdog has held the stage
            self._estimator_measures(rotation=None, tilts=None)
            try:
                if state != "stopped" and stage_reachable:  # a finished run releases the watchdog
                    self.stage.request("disarm", {"owner": self.owner})
            except (CommandError, ServiceUnavailable) as error:
                log.warning("disarming the stage watchdog failed: %s", error)
        run["outcome"] = {"state": state, "reason": reason, "finished_at_ns": time.time_ns(),
                          "iterations": run["iterations"], **({"recovered": True} if recovered else {})}
        run["stage_log"] = []
        if not stage_reachable:  # asking a dead stage again only delays the end (the gateway asks later)
            run["outcome"]["stage_log_error"] = "the stage service was unreachable when the run ended"
        else:
            try:
                run["stage_log"] = self.stage.request("log", {"since_ns": run["started_at_ns"]}).get("entries", [])
            except (CommandError, ServiceUnavailable) as error:
                run["outcome"]["stage_log_error"] = str(error)
        self._write_summary()
        log.info("run %s %s: %s after %d iterations", run["id"], state, reason, run["iterations"])
        self._status()

    # -- the loop ----------------------------------------------------------------------
    def on_estimate(self, estimate: MotionEstimate) -> dict | None:
        """One estimate in; the iteration record out (None when no run is active)."""
        run = self.run
        if self.state != "servoing" or run is None:
            return None
        if estimate.reference_id != run["reference_id"]:
            # One or two may be in flight from before the run's reference was taught;
            # a third in a row means the estimator now measures against another one.
            self.foreign_estimates += 1
            if self.foreign_estimates >= FOREIGN_ESTIMATES_TO_FAIL:
                self._finish("failed", f"the reference changed during the run: the estimator now measures against "
                                       f"{estimate.reference_id}, not the run's {run['reference_id']} (taught again?)")
            return None
        self.foreign_estimates = 0
        self.last_estimate_at = self.clock()
        scan_started = estimate.frame_scan_started_at_ns or estimate.frame_acquired_at_ns
        record = {
            "seq": estimate.seq, "dx_px": estimate.dx_px, "dy_px": estimate.dy_px,
            "rotation_deg": estimate.rotation_deg, "confidence": estimate.confidence, "snr_db": estimate.snr_db,
            "pixel_size_nm": estimate.pixel_size_nm, "frame_acquired_at_ns": estimate.frame_acquired_at_ns,
            "frame_published_at_ns": estimate.frame_published_at_ns,
            "estimate_published_at_ns": estimate.published_at_ns,
            "frame_source_interval_s": estimate.frame_source_interval_s,
        }
        if estimate.pixel_size_nm is None:
            # Pixels cannot become micrometres: never guess the scale of a real stage's move.
            self._record(record, "held: pixel size unknown")
            self._finish("failed", "the frames carry no pixel size (their files or source do not say): set "
                                   "SEMSERVO_IMAGESERVER__PIXEL_SIZE_NM (or the magnification) and start again")
            return record
        if scan_started < run["last_command_ns"]:
            run["held_stale"] += 1
            return self._record(record, "held: stale (scanned during the last move)")
        if estimate.confidence < self.settings.min_confidence:
            run["low_confidence"] += 1
            if run["low_confidence"] >= self.settings.lost_after:
                self._record(record, "held: low confidence")
                self._finish("failed", f"scene lost: {run['low_confidence']} low-confidence frames in a row")
                return record
            return self._record(record, "held: low confidence")
        run["low_confidence"] = 0

        translation = math.hypot(estimate.dx_px, estimate.dy_px)
        record["error_px"] = translation
        tilt_step = self._tilt_step(estimate, record) if self.tilt_law is not None else None
        # Converged (by default) when the mean of the last N fresh errors is under the
        # tolerance: the mean, not each one, so estimation noise or vibration near the
        # tolerance cannot keep a finished run going; converge_on="each" asks it of each.
        recent = run.setdefault("recent", [])
        recent.append((estimate.dx_px, estimate.dy_px, estimate.rotation_deg))
        del recent[:-self.settings.converge_frames]
        mean_dx, mean_dy, mean_rotation = np.mean(recent, axis=0)
        record["mean_error_px"] = float(math.hypot(mean_dx, mean_dy))  # what convergence is judged on
        within = len(recent) == self.settings.converge_frames and self._within(mean_dx, mean_dy, mean_rotation)
        if self.settings.converge_on == "each":
            # The stopping rule picks a lucky moment: ending on the first mean under
            # tolerance leaves the truth near the tolerance; asking it of every frame
            # leaves it well inside (measured in bench/positioning.py).
            within = within and all(self._within(*error) for error in recent)
        if within and not self.settings.hold:
            self._record(record, "within tolerance")
            self._finish("converged", f"mean error of the last {len(recent)} fresh frames "
                                      f"{math.hypot(mean_dx, mean_dy):.3f} px, under {self.settings.tolerance_px:g} px")
            return record
        if run["iterations"] >= self.settings.max_iterations:
            self._finish("failed", f"iteration limit ({self.settings.max_iterations}) reached")
            return record

        end_s = estimate.frame_source_interval_s[1] if estimate.frame_source_interval_s else None
        sampling_time = self._sampling_time(estimate, end_s)
        if self.law.dofs:
            step = self.law.step(estimate.dx_px, estimate.dy_px, estimate.rotation_deg, estimate.pixel_size_nm,
                                 sampling_time)
        else:  # tilts only
            step = {"error": [], "cost": 0.0, "gain": 0.0, "velocity": [], "move": {}}
        cost = step["cost"]
        run["min_cost"] = min(run["min_cost"], cost)
        # Divergence is judged against the best cost so far, but never against less than
        # the square of diverge_floor_px (or of 5 x tolerance): near the target the cost
        # is estimation noise and vibration, whatever tolerance the run asks for.
        floor = max(5 * self.settings.tolerance_px, self.settings.diverge_floor_px) ** 2
        run["rising"] = run["rising"] + 1 if cost > self.settings.diverge_factor * max(run["min_cost"], floor) else 0
        move = dict(step["move"])
        planar = math.hypot(move.get("x_um", 0.0), move.get("y_um", 0.0))
        saturated = planar > self.settings.max_move_um
        if saturated:
            scale = self.settings.max_move_um / planar
            for key in ("x_um", "y_um"):
                if key in move:
                    move[key] *= scale
        record.update(error=step["error"], cost=cost, gain=step["gain"], velocity=step["velocity"],
                      sampling_time_s=sampling_time, move=move, saturated=saturated)
        if run["rising"] >= self.settings.diverge_iterations:
            self._record(record, "held: diverging")
            self._finish("failed", f"diverging: cost above {self.settings.diverge_factor:g}x its minimum for "
                                   f"{run['rising']} moves")
            return record
        targets = {axis: move[f"{axis}_um"] for axis in ("x", "y") if f"{axis}_um" in move}
        turns = {axis: move[axis] for axis in ("rotation_deg",) if axis in move}
        if tilt_step is not None:
            turns.update(tilt_step["move"])
        for axis, value in turns.items():  # saturation, as for the planar move
            if abs(value) > self.settings.max_turn_deg:
                turns[axis] = math.copysign(self.settings.max_turn_deg, value)
                record["saturated"] = True
        if turns:
            record["turn_deg"] = turns
        if not targets and not turns:  # a tilts-only run between two sweeps: nothing to move yet
            return self._record(record, "held: waiting for a focus sweep")
        try:
            if targets:
                written = self.stage.request("move", {"targets": targets, "relative": True, "owner": self.owner})
                record["command_written_at_ns"] = written["written_at_ns"]
                record["voltages"] = written["voltages"]
                record["positions_um"] = written["positions_um"]
            if turns:
                turned = self.stage.request("rotate", {"targets": turns, "relative": True, "owner": self.owner})
                record.setdefault("command_written_at_ns", turned["written_at_ns"])
                record["angles_deg"] = turned["angles_deg"]
                # Frames scanned before the turn or tilt has arrived show a pose in between.
                settled = turned.get("settled_at_ns", turned["written_at_ns"])
                record["command_settled_at_ns"] = settled
                if tilt_step is not None:
                    run["tilt_settled_ns"] = settled
                    run["tilt_iterations"] += 1
                    # A tilt about the pivot below the surface shifts the view: the planar
                    # cost jumps by design, so divergence is judged afresh from here.
                    run["min_cost"], run["rising"] = math.inf, 0
        except CommandError as refusal:
            self._record(record, f"refused by the stage: {refusal.code}")
            if refusal.code == "stopped":
                # An operator's stop reaches the stage first (it must hold at once) and this
                # controller a moment later: a move in between is refused, and the run was
                # stopped, not failed.
                self._finish("stopped", f"the stage was stopped: {refusal.message}")
            else:
                self._finish("failed", f"the stage refused the move ({refusal.code}): {refusal.message}")
            return record
        except ServiceUnavailable as error:
            self._record(record, "stage unreachable")
            self._finish("failed", f"the stage service is unreachable: {error}", stage_reachable=False)
            return record
        run["iterations"] += 1
        run["last_command_ns"] = max(record["command_written_at_ns"], record.get("command_settled_at_ns", 0))
        run["last_source_end_s"] = end_s
        run["last_acted_acquired_ns"] = estimate.frame_acquired_at_ns
        self.last_heartbeat = self.clock()
        record["latency_ms"] = (record["command_written_at_ns"] - estimate.frame_published_at_ns) / 1e6
        return self._record(record, "moved")

    def _tilt_step(self, estimate: MotionEstimate, record: dict) -> dict | None:
        """The tilts' part of an iteration: acted on once per focus sweep, and only for a
        sweep scanned after the last tilt move had arrived; held within tolerance (the
        run converges on that measurement) or when the sweep could not tell the tilts."""
        run = self.run
        record.update(alpha_deg=estimate.alpha_deg, beta_deg=estimate.beta_deg,
                      tilt_confidence=estimate.tilt_confidence, tilt_seq=estimate.tilt_seq)
        started = estimate.tilt_scan_started_at_ns
        if estimate.tilt_seq is None or estimate.tilt_seq == run["last_tilt_seq"] or started is None:
            return None
        run["last_tilt_seq"] = estimate.tilt_seq
        if started < run["tilt_settled_ns"]:
            record["tilt_action"] = "held: sweep scanned during the last tilt move"
            return None
        if estimate.alpha_deg is None or estimate.beta_deg is None \
                or (estimate.tilt_confidence or 0.0) < self.settings.min_tilt_confidence:
            record["tilt_action"] = "held: tilts not measured with confidence"
            return None
        errors = {"alpha": estimate.alpha_deg, "beta": estimate.beta_deg}
        record["tilt_frames"] = estimate.tilt_frames
        largest = max(abs(errors[dof]) for dof in self.tilt_law.dofs)
        # Within tolerance, the run may converge on this measurement; the tilts are still
        # corrected down to half the tolerance, or the run would end at its edge.
        within = largest <= self.settings.tolerance_tilt_deg
        run["tilt_error"] = {dof: errors[dof] for dof in self.tilt_law.dofs} if within else None
        if largest <= self.settings.tolerance_tilt_deg / 2:
            record["tilt_action"] = "within tolerance"
            return None
        interval = estimate.tilt_source_interval_s
        end_s = interval[1] if interval else None
        if end_s is not None and run["last_tilt_end_s"] is not None:
            sampling_time = max(end_s - run["last_tilt_end_s"], 1e-3)
        elif interval:
            sampling_time = max(2 * (interval[1] - interval[0]), 1e-3)
        else:
            sampling_time = max(estimate.tilt_sweep_s or 1.0, 1e-3)
        run["last_tilt_end_s"] = end_s
        step = self.tilt_law.step(estimate.alpha_deg, estimate.beta_deg, sampling_time)
        record.update(tilt_error=step["error"], tilt_cost=step["cost"], tilt_gain=step["gain"],
                      tilt_velocity=step["velocity"], tilt_sampling_time_s=sampling_time, tilt_action="moved")
        return step

    def _sampling_time(self, estimate: MotionEstimate, end_s: float | None) -> float:
        """The measured time between this iteration and the last (eq. 37), on the image
        source's clock when it has one (the fake lab's simulated time), else the frames'
        acquisition times. The first iteration takes two scan durations: a fresh frame
        comes every second scan."""
        run = self.run
        if end_s is not None and run["last_source_end_s"] is not None:
            return max(end_s - run["last_source_end_s"], 1e-3)
        if end_s is None and run.get("last_acted_acquired_ns"):
            return max((estimate.frame_acquired_at_ns - run["last_acted_acquired_ns"]) / 1e9, 1e-3)
        if estimate.frame_source_interval_s:
            start, end = estimate.frame_source_interval_s
            return max(2 * (end - start), 1e-3)
        return 0.5

    def tick(self) -> float:
        """Periodic work: keep the stage's watchdog fed while servoing (a dead
        controller stops feeding it, and the stage holds)."""
        if self.state != "servoing":
            return 0.5
        now = self.clock()
        silent = now - self.last_estimate_at
        if silent > self.settings.estimate_timeout_s:
            self._finish("failed", f"no estimate against the run's reference for {silent:.1f} s: "
                                   f"{self._estimator_account()}")
            return 0.5
        if now - self.last_heartbeat >= self.watchdog_s / 3:
            try:
                reply = self.stage.request("heartbeat", {"owner": self.owner})
                self.last_heartbeat = now
                if reply.get("state") != "ready":
                    reason = f": {reply['reason']}" if reply.get("reason") else ""
                    self._finish("failed", f"the stage is {reply.get('state')}{reason}")
            except ServiceUnavailable as error:
                self._finish("failed", f"the stage service is unreachable: {error}", stage_reachable=False)
            except CommandError as error:
                self._finish("failed", f"the stage refused a heartbeat: {error}")
        return self.watchdog_s / 6

    # -- records -----------------------------------------------------------------------
    def _record(self, record: dict, action: str) -> dict:
        record["action"] = action
        record["t_ns"] = time.time_ns()
        record["iteration"] = self.run["iterations"]
        self.run["records"].append(record)
        if self._journal is not None:
            self._journal.write(json.dumps(record, default=_jsonable) + "\n")
            self._journal.flush()
        self.publish("iteration", record)
        return record

    def _open_journal(self) -> None:
        self._close_journal()
        if self.runs_dir is None:
            return
        self.runs_dir.mkdir(parents=True, exist_ok=True)
        self._journal = open(self.runs_dir / f"{self.run['id']}.jsonl", "w", encoding="utf-8")  # noqa: SIM115
        # The header: what a controller started after this one dies needs to finish the run.
        header = {key: self.run[key] for key in ("id", "reference_id", "settings", "started_at_ns", "stage_at_start")}
        self._journal.write(json.dumps({"header": header, "owner": self.owner}, default=_jsonable) + "\n")
        self._journal.flush()

    def _close_journal(self) -> None:
        if self._journal is not None:
            self._journal.close()
            self._journal = None

    def _write_summary(self) -> None:
        self._close_journal()
        if self.runs_dir is None:
            return
        path = self.runs_dir / f"{self.run['id']}.json"
        path.write_text(json.dumps(self.record(), default=_jsonable, indent=1))
        self.run["path"] = str(path)

    def recover(self) -> list[str]:
        """Finish the runs a dead controller left (a journal without its summary) as
        ``failed``, with their iterations and the stage's command log since they began.
        Returns their ids; the last one becomes this controller's last run."""
        if self.runs_dir is None or not self.runs_dir.is_dir():
            return []
        recovered = []
        for journal in sorted(self.runs_dir.glob("*.jsonl")):
            if journal.with_suffix(".json").exists():
                continue
            run = _read_journal(journal)
            if run is None:
                log.error("cannot read the journal %s: left as it is", journal)
                continue
            self.run = run
            self._finish("failed", "the controller stopped mid-run (killed or crashed); finished from its journal "
                                   "when the controller started again", recovered=True)
            recovered.append(run["id"])
        return recovered

    def stored(self, run_id: str) -> dict | None:
        """A finished run's record by id (the active or last one, or its summary file)."""
        if self.run is not None and self.run["id"] == run_id:
            return self.record()
        if self.runs_dir is None or not _RUN_ID.fullmatch(run_id):
            return None
        path = self.runs_dir / f"{run_id}.json"
        return json.loads(path.read_text()) if path.is_file() else None

    def record(self) -> dict:
        """The active or last run's full record."""
        if self.run is None:
            return {}
        record = {key: value for key, value in self.run.items() if not key.startswith("last_")}
        record["min_cost"] = None if math.isinf(record["min_cost"]) else record["min_cost"]
        return record

    def status(self) -> dict:
        run = self.run or {}
        records = run.get("records", [])
        # The error now: of the last fresh frame (one scanned during a move shows a pose in between).
        last = next((r for r in reversed(records) if "error_px" in r and not r.get("action", "").startswith("held: stale")),
                    None)
        last_moved = next((r for r in reversed(records) if r.get("action") == "moved"), None)
        return {
            "state": self.state, "reason": self.reason, "run_id": run.get("id"),
            "iteration": run.get("iterations", 0), "error_px": last and last["error_px"],
            "mean_error_px": last and last.get("mean_error_px"),
            "error_um": last and last["pixel_size_nm"] and last["error_px"] * last["pixel_size_nm"] / 1000,
            "cost": last and last.get("cost"), "rotation_deg": last and last["rotation_deg"],
            "alpha_deg": next((r["alpha_deg"] for r in reversed(records) if r.get("alpha_deg") is not None), None),
            "beta_deg": next((r["beta_deg"] for r in reversed(records) if r.get("beta_deg") is not None), None),
            "tilt_iterations": run.get("tilt_iterations", 0),
            "last_latency_ms": last_moved and last_moved["latency_ms"],
            "held_stale": run.get("held_stale", 0), "path": run.get("path"),
        }

    def _status(self) -> None:
        self.publish("status", self.status())


#: Estimates in a row against another reference before the run fails (one or two may be
#: in flight from before the run's reference was taught).
FOREIGN_ESTIMATES_TO_FAIL = 3

_RUN_ID = re.compile(r"[0-9]{8}-[0-9]{6}-[0-9a-f]{6}")


def _read_journal(path: Path) -> dict | None:
    """A run as its journal left it: the header, then every iteration written."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
        header = json.loads(lines[0])["header"]
    except (OSError, ValueError, KeyError, IndexError, TypeError):
        return None
    records = []
    for line in lines[1:]:
        try:
            records.append(json.loads(line))
        except ValueError:
            break  # the line being written when the process died
    moved = [record for record in records if record.get("action") == "moved"]
    return {**header, "iterations": len(moved), "records": records, "outcome": None,
            "min_cost": min((r["cost"] for r in records if r.get("cost") is not None), default=math.inf)}


def _jsonable(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON serializable")
