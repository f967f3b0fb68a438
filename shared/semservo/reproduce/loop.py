"""One positioning trial in process: the simulated lab (its SEM, its piezo stage with
hysteresis, drift and vibration) on a clock that advances by each scan's time, a motion
measurement (:mod:`.methods`) and a control law (the paper's,
:class:`semservo.control.ControlLaw`, eq. 30-37, or :class:`semservo.control.PositionLaw`).
Every method closes this same loop, from the same start, on the same frames' physics;
the truth comes from the simulator.

Two loops:

* :func:`run_trial` (Tables II-IV): one frame per iteration, the clock advancing by each
  scan, every frame acted on;
* :func:`run_timed_trial` (time to target): the SEM scans without pause, as a real one
  does; a decision comes ``latency_s`` after a frame ends, and the move lands during the
  next scan, which therefore shows a pose in between and is not acted on. A frame is
  *fresh* when its scan starts after the last move has settled (by the stage's settling
  model, :class:`semservo.control.StageSettling`, as the stage service reports it), so the
  paper's law gets a fresh frame every second scan, as on the real instrument. The stage's
  displacement model may be the lab's (``calibrated``), a linear one from the nominal
  stroke (``uncalibrated``) or another stage's (``other-stage+15%``, ``other-stage-15%``).

It leaves out the services (sockets, serial line) that the whole-stack benchmarks
(``bench/positioning.py``, ``bench/tilt.py``) include: here the question is what each
method does with the frames, not how fast the wires are.
"""

from __future__ import annotations

import copy
import math
from dataclasses import asdict, dataclass, replace

import cv2
import numpy as np

from semservo.control import (
    MODEL_UNCERTAINTY, AdaptiveGain, ControlLaw, StageSettling, UnexpectedResponse, make_law, move_pieces,
    planar_limit_um, saturate_planar,
)
from semservo.config import StageSettings
from semservo.estimation import MotionEstimator
from semservo.estimation.raster import rows_scanned_after
from semservo.reproduce import methods
from semservo.simulation.sem import ScanSettings
from semservo.simulation.world import HOME_VOLTAGE, PRESETS, Disturbances, World
from semservo.stage_model import BranchModel, LinearModel

#: The stage's displacement models a timed trial can drive the stage through.
STAGE_MODELS = ("calibrated", "uncalibrated", "other-stage+15%", "other-stage-15%")
#: The nominal stroke: 100 um over the NV 40/3's -20..130 V (what is known without a calibration).
NOMINAL_UM_PER_V = 100.0 / 150.0


class ScaledModel:
    """Another stage's model: a displacement model whose axis moves ``scale`` times what
    the model of this stage expects (a model from another stage, miscalibrated by
    ``scale`` - 1). Same interface as :class:`semservo.stage_model.BranchModel`."""

    def __init__(self, inner, scale: float):
        self.inner, self.scale = inner, scale

    @property
    def position_um(self) -> float:
        return self.inner.position_um / self.scale

    def voltage_for(self, target_um: float) -> float:
        return self.inner.voltage_for(target_um * self.scale)

    def reset(self, position_um: float) -> None:
        self.inner.reset(position_um * self.scale)

    def position_for(self, voltage: float) -> float:
        return self.inner.position_for(voltage) / self.scale

    def follow_voltage(self, voltage: float, previous_voltage: float) -> None:
        self.inner.follow_voltage(voltage, previous_voltage)


def displacement_model(kind: str, axis: str):
    """The displacement model ``kind`` (one of :data:`STAGE_MODELS`) for axis "x" or "y"."""
    if kind == "calibrated":
        return BranchModel.tritor(axis)
    if kind == "uncalibrated":
        return LinearModel(NOMINAL_UM_PER_V, -20.0)
    if kind.startswith("other-stage"):
        # The lab's model for a stage that moves 15 % more (or less) than this one's: this
        # stage moves 1 / 1.15 (or 1 / 0.85) of what that model expects.
        return ScaledModel(BranchModel.tritor(axis), 1.0 / (1.0 + float(kind[len("other-stage"):-1]) / 100.0))
    raise ValueError(f"unknown stage model {kind!r}; models: {', '.join(STAGE_MODELS)}")


class ManualClock:
    """Simulated seconds that pass only when told (a scan's time)."""

    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@dataclass(frozen=True)
class TrialSettings:
    tolerance_px: float = 0.1
    converge_frames: int = 3
    max_iterations: int = 150
    #: Simulated seconds (scans) before the trial is given up, whatever the iterations
    #: (None: the iteration limit alone): the same for every method.
    time_budget_s: float | None = None
    lost_after: int = 5
    max_move_um: float = 10.0
    reference_frames: int = 4


#: What a chained move's pieces wait for besides the settling, as from the stage
#: service's ``ready_at_ns`` with its default limits: until a step of the largest size
#: one command may ask is within the rate limit.
CHAIN_INTERVAL_S = (StageSettings.model_fields["max_step_v"].default
                    / StageSettings.model_fields["max_rate_v_per_s"].default)


#: The simulated SEM's sample, rasterized and blurred to each level, for the last (case,
#: seed) a lab was made for: pure data (``SEM.render`` is pure given its inputs) and most
#: of a new lab's cost, so consecutive labs of one preset and seed share it (one kept:
#: ~100 MB each).
_SAMPLE_STACKS: dict = {}


class Lab:
    """The simulated lab of one case, stepped by hand."""

    def __init__(self, case: str, seed: int, reference_dwell_ns: float | None = None, stage_model: str = "calibrated",
                 settling: StageSettling | None = None, phase_walk_rad_per_sqrt_s: float = 0.0):
        self.preset = PRESETS[case]
        self.clock = ManualClock()
        # ``phase_walk_rad_per_sqrt_s``: vibration lines that wander (Disturbances), not
        # the default's steady tones.
        self.world = World(self.preset, speedup=1.0, seed=seed, clock=self.clock,
                           disturbances=Disturbances(phase_walk_rad_per_sqrt_s=phase_walk_rad_per_sqrt_s,
                                                     walk_seed=seed))
        self._sample_key = (case, seed)
        if self._sample_key in _SAMPLE_STACKS:
            self.world.sem._stacks = dict(_SAMPLE_STACKS[self._sample_key])
        self.settings = ScanSettings(dwell_ns=self.preset.dwell_ns, magnification=self.preset.magnification,
                                     working_distance_um=self.preset.focus_um)
        self.reference_dwell_ns = reference_dwell_ns or self.preset.reference_dwell_ns
        self.models = {0: displacement_model(stage_model, "x"), 1: displacement_model(stage_model, "y")}
        self.settling = settling or StageSettling()
        for channel, model in self.models.items():
            model.reset(model.position_for(HOME_VOLTAGE))

    @property
    def pixel_um(self) -> float:
        return self.settings.pixel_um

    def _keep_sample(self) -> None:
        if _SAMPLE_STACKS.get(self._sample_key) is not self.world.sem._stacks:
            _SAMPLE_STACKS.clear()
            _SAMPLE_STACKS[self._sample_key] = self.world.sem._stacks

    def scan(self, dwell_ns: float | None = None) -> tuple[np.ndarray, tuple[float, float]]:
        settings = self.settings if dwell_ns is None else replace(self.settings, dwell_ns=dwell_ns)
        pixels, start, end = self.world.scan(settings, wait=False)
        self._keep_sample()
        self.clock.t = end + 1e-3
        return pixels, (start, end)

    def true_pose(self, interval: tuple[float, float], *, vibration: bool = True) -> np.ndarray:
        """The sample's pose (um) averaged over ``interval``: what a frame scanned then
        shows; without the vibration, where the sample rested meanwhile."""
        samples = [self.world.pose(t, vibration=vibration) for t in np.linspace(interval[0], interval[1], 32)]
        return np.array([[p.x_um, p.y_um] for p in samples]).mean(axis=0)

    def move(self, dx_um: float, dy_um: float, at: float | None = None) -> dict[str, float]:
        """A relative stage move through the lab's displacement model, as the stage service
        makes it, written at simulated time ``at`` (None: now, and the clock then waits
        10 ms for the piezo)."""
        voltages = {}
        for channel, delta in ((0, dx_um), (1, dy_um)):
            model = self.models[channel]
            voltage = float(np.clip(model.voltage_for(model.position_um + delta), -20.0, 120.0))
            self.world.set_voltage(channel, voltage, self.clock.t if at is None else at)
            voltages["xy"[channel]] = voltage
        if at is None:
            self.clock.t += 0.01  # the piezo settles in milliseconds
        return voltages

    def move_in_pieces(self, move: dict[str, float], max_move_um: float, at: float) -> tuple[list, float, float]:
        """A planar move (``x_um``, ``y_um``) made as the controller makes it: in pieces of
        at most ``max_move_um`` (:func:`semservo.control.move_pieces`), each written once
        the one before has settled and the stage service's ``ready_at_ns`` has passed
        (:data:`CHAIN_INTERVAL_S`). Returns the voltages after each piece, when the last
        was written and when it will have settled (simulated s)."""
        voltages, written_at, settled_at = [], at, at
        for piece in move_pieces(move, max_move_um):
            voltages.append(self.move(piece.get("x_um", 0.0), piece.get("y_um", 0.0), at=at))
            written_at = at
            settled_at = at + self.settling.after_s(piece)
            at = max(settled_at, at + CHAIN_INTERVAL_S)
        return voltages, written_at, settled_at

    def jog(self, dx_um: float, dy_um: float) -> dict[str, float]:
        """The trial's starting offset, exact on the simulated stage: the voltage that
        moves the axis's static displacement by (``dx_um``, ``dy_um``) from where it
        rests, found on the simulator's own hysteresis (bisection on a copy), so every
        stage model and every version of the models starts the same true distance from
        the target (through a model, the offset depended on the model: a start of 30 %
        of the field went 24 % of it through the branch model with an offset after a
        reversal, 35 % through Masing's rule). The lab's model then reads its position
        from the voltages, as a stage service does after the operator's jog."""
        voltages = {}
        for channel, delta in ((0, dx_um), (1, dy_um)):
            hysteresis = self.world.axes[channel].hysteresis
            goal = hysteresis.displacement + delta
            low, high = -20.0, 120.0
            for _ in range(50):
                middle = (low + high) / 2
                if copy.deepcopy(hysteresis).apply(middle) < goal:
                    low = middle
                else:
                    high = middle
            voltage = (low + high) / 2
            self.world.set_voltage(channel, voltage, self.clock.t)
            self.models[channel].follow_voltage(voltage, HOME_VOLTAGE)
            voltages["xy"[channel]] = voltage
        self.clock.t += 0.01
        return voltages

    def scan_at(self, start: float, dwell_ns: float | None = None) -> tuple[np.ndarray, tuple[float, float]]:
        """A frame whose scan starts at simulated time ``start``."""
        self.clock.t = start
        settings = self.settings if dwell_ns is None else replace(self.settings, dwell_ns=dwell_ns)
        pixels, start, end = self.world.scan(settings, wait=False)
        self._keep_sample()
        self.clock.t = end
        return pixels, (start, end)


def mask_of(reference: np.ndarray) -> np.ndarray:
    """The paper's case 6: a binary mask of the part by intensity thresholding (Otsu)."""
    eight = cv2.normalize(reference.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    _, mask = cv2.threshold(cv2.GaussianBlur(eight, (0, 0), 2.0), 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return mask > 0


def run_trial(case: str, method: str, start_um: tuple[float, float], *, seed: int = 1,
              settings: TrialSettings = TrialSettings(), reference_dwell_ns: float | None = None,
              keep_images: bool = False) -> dict:
    """One trial: teach at home, displace by ``start_um``, servo with ``method`` until the
    mean error of the last frames is under tolerance, the scene is lost, or the
    iteration limit. Returns the outcome, per-iteration records, the true final error
    (um, from the simulator) and, with ``keep_images``, the desired and final images."""
    lab = Lab(case, seed, reference_dwell_ns)
    frames, intervals = zip(*(lab.scan(lab.reference_dwell_ns) for _ in range(settings.reference_frames)))
    reference = np.mean(frames, axis=0, dtype=np.float32)
    taught = lab.true_pose((intervals[0][0], intervals[-1][1]))
    mask = None
    desired = reference
    if lab.preset.mask_reference:
        mask = mask_of(reference)
        desired = mask.astype(np.float32) * 255  # what a baseline sees: the mask itself
    measure = methods.make(method, desired if method != "semservo" else reference, mask=mask)
    lab.move(*start_um)
    law = ControlLaw(("x", "y"), AdaptiveGain(), integral_time_s=10.0)
    pixel_nm = lab.pixel_um * 1000
    records, recent, lost = [], [], 0
    outcome, reason = "failed", f"iteration limit ({settings.max_iterations}) reached"
    frame, interval = lab.scan()
    last_end = None
    began = interval[0]
    for iteration in range(settings.max_iterations):
        if settings.time_budget_s is not None and interval[1] - began > settings.time_budget_s:
            reason = f"time budget ({settings.time_budget_s:g} s) spent"
            break
        measured = measure(frame)
        record = {"iteration": iteration, "compute_ms": measured.compute_ms, "ok": measured.ok}
        if not measured.ok:
            lost += 1
            record["action"] = f"held: {measured.reason}"
            records.append(record)
            if lost >= settings.lost_after:
                outcome, reason = "failed", f"scene lost: {measured.reason}"
                break
            frame, interval = lab.scan()
            continue
        lost = 0
        error_px = math.hypot(measured.dx, measured.dy)
        recent = (recent + [(measured.dx, measured.dy)])[-settings.converge_frames:]
        record.update(dx_px=measured.dx, dy_px=measured.dy, error_px=error_px)
        if len(recent) == settings.converge_frames and math.hypot(*np.mean(recent, axis=0)) <= settings.tolerance_px:
            record["action"] = "within tolerance"
            records.append(record)
            outcome, reason = "converged", ""
            break
        if error_px > 0.45 * frame.shape[1]:
            record["action"] = "held: beyond the field"
            records.append(record)
            outcome, reason = "failed", f"measured {error_px:.0f} px: beyond half the field (lost or diverged)"
            break
        sampling = interval[1] - last_end if last_end is not None else 2 * (interval[1] - interval[0])
        last_end = interval[1]
        step = law.step(measured.dx, measured.dy, 0.0, pixel_nm, sampling)
        move, _ = saturate_planar(step.move, settings.max_move_um)
        record.update(cost=step.cost, gain=step.gain, voltages=lab.move(move["x_um"], move["y_um"]),
                      action="moved")
        records.append(record)
        frame, interval = lab.scan()
    final = lab.true_pose(interval) - taught
    result = {
        "case": case, "method": method, "start_um": list(start_um), "seed": seed, "outcome": outcome,
        "reason": reason, "iterations": sum(1 for r in records if r.get("action") == "moved"), "records": records,
        "true_error_um": final.tolist(), "true_error_px": float(np.hypot(*final) / lab.pixel_um),
        "compute_ms": float(np.mean([r["compute_ms"] for r in records])) if records else None,
        "frame_time_s": lab.settings.frame_time_s, "pixel_um": lab.pixel_um, "settings": asdict(settings),
    }
    if keep_images:
        result["desired"] = desired
        result["final"] = frame
    return result


@dataclass(frozen=True)
class TimedSettings:
    """A timed trial's settings (:func:`run_timed_trial`); the controller's defaults where
    it has them."""

    tolerance_px: float = 0.1
    #: The paper's law: converged when the error of the mean of this many fresh frames is
    #: under tolerance (the controller's rule when these results were measured; the
    #: controller now takes the mean of the errors' sizes, which is stricter). The position law decides it itself
    #: (:attr:`semservo.control.PositionLaw.converged`).
    converge_frames: int = 3
    max_iterations: int = 150  # fresh frames acted on
    #: Simulated seconds before the run is given up (None: only the iteration limit).
    time_budget_s: float | None = None
    lost_after: int = 5
    max_move_um: float = 10.0
    #: The position law: once the stage has responded as commanded, a planar move of up to
    #: this many ``max_move_um``, made in pieces (as the controller's ``moves_per_frame``).
    max_moves: int = 3
    reference_frames: int = 4
    #: From a frame's end to the move's write: transfer, estimate, decision, serial line.
    latency_s: float = 0.05
    #: semservo's shifts averaged over the scan's bands of rows
    #: (:mod:`semservo.estimation.raster`, on by default as in the estimator service);
    #: both laws see the same estimates.
    scan_averaged: bool = True
    #: ... fitting the stage's vibration lines, learned at the teach from its frames at
    #: rest (:meth:`semservo.estimation.MotionEstimator.learn_vibration`), as the
    #: estimator service does; False: the bands' random-effects mean.
    vibration_lines: bool = True
    #: The simulated vibration's lines wander by this random walk of their phase
    #: (radians per square root of a second; :class:`~semservo.simulation.world.Disturbances`);
    #: 0, the default: steady tones.
    phase_walk_rad_per_sqrt_s: float = 0.0
    #: After the start jog, before the run starts (the jog's settling and early creep).
    start_after_s: float = 1.0
    #: ... plus a part of this drawn from the trial's seed and start (the same for every
    #: law and stage model): trials then meet the stage's vibration (7-93 Hz) at random
    #: phases. Without it every trial of a preset scanned its frames at the same times
    #: after teaching, and its errors of one sign from the 7 Hz vibration's phase at
    #: ×5000 repeated in all of them.
    start_jitter_s: float = 1.0
    #: Act on partial frames (semservo's measurement only): the rows of the scan a move
    #: lands in that were scanned after it settled, when they are at least
    #: :data:`semservo.estimation.raster.PARTIAL_FRAME_FROM` of the scan, instead of waiting for
    #: the next whole scan (the estimator service's ``partial_frames``).
    partial_frames: bool = False
    #: Keep servoing this long after converging (0: stop there), counting the corrections.
    hold_s: float = 0.0
    integral_time_s: float | None = 10.0  # the paper's law, as in run_trial


def _law_for(name: str, model: str, settings: TimedSettings, noise_px: float):
    # The position law is told how far to trust the stage's model: a run knows whether its
    # stage service loaded a calibration (a miscalibrated one looks calibrated).
    return make_law(name, ("x", "y"), gain=AdaptiveGain(), integral_time_s=settings.integral_time_s,
                    model_uncertainty=MODEL_UNCERTAINTY["uncalibrated" if model == "uncalibrated" else "calibrated"],
                    noise_px=noise_px,
                    tolerance_px=settings.tolerance_px, max_move_um=settings.max_move_um,
                    max_moves=settings.max_moves, partial_frames=settings.partial_frames)


@dataclass(frozen=True)
class Taught:
    """What teaching at home left: the reference (and the mask a baseline sees in the mask
    preset), the pose it was taught at, the estimate's noise per frame at rest (px) and
    when teaching ended (simulated s). The same for every law, method and stage model of
    one lab seed: trials share it rather than scan it again."""

    reference: np.ndarray
    mask: np.ndarray | None
    taught_um: tuple[float, float]
    noise_px: float
    ended_s: float
    #: The simulated SEM's charging of the sample when teaching ended (the scans so far
    #: brightened the field they covered) and its noise generator's state: a lab that
    #: starts here continues both (a fresh generator of the same seed would repeat the
    #: noise of the reference's own scans, a false correlation peak).
    charge: np.ndarray | None = None
    noise_state: dict | None = None
    #: Where the sample rested while the reference was scanned (the vibration left out):
    #: what a trial's ``stage_error_px`` is measured from.
    resting_um: tuple[float, float] | None = None
    #: The stage's vibration lines (Hz) learned from the frames at rest, and the live
    #: scan's time per row they are fitted with.
    vibration_hz: tuple[float, ...] = ()
    line_time_s: float | None = None

    def start(self, lab: "Lab") -> None:
        """Put a fresh lab of the same case and seed where teaching left its own: its
        frames are then the ones the teaching lab would have scanned."""
        lab.clock.t = self.ended_s
        if self.charge is not None:
            lab.world.sem.charge = self.charge.copy()
        if self.noise_state is not None:
            lab.world.rng.bit_generator.state = self.noise_state

    def measure(self, method: str, scan_averaged: bool = False):
        desired = self.reference if method == "semservo" or self.mask is None \
            else self.mask.astype(np.float32) * 255  # what a baseline sees: the mask itself
        return methods.make(method, desired, mask=self.mask, scan_averaged=scan_averaged,
                            vibration_hz=self.vibration_hz if method == "semservo" else (),
                            line_time_s=self.line_time_s)


def teach(lab: Lab, settings) -> Taught:
    """The reference (``reference_frames`` scans at the reference dwell, averaged), the
    pose it was taught at, and the estimate's noise per frame at rest: the scatter of as
    many frames at the live dwell measured against it (semservo's estimator)."""
    frames, intervals = zip(*(lab.scan(lab.reference_dwell_ns) for _ in range(settings.reference_frames)))
    reference = np.mean(frames, axis=0, dtype=np.float32)
    taught = lab.true_pose((intervals[0][0], intervals[-1][1]))
    resting = lab.true_pose((intervals[0][0], intervals[-1][1]), vibration=False)
    mask = mask_of(reference) if lab.preset.mask_reference else None
    at_rest = [lab.scan()[0] for _ in range(settings.reference_frames)]
    line_time = lab.settings.line_time_s
    vibration_hz = ()
    if settings.scan_averaged and settings.vibration_lines and mask is None:
        estimator = MotionEstimator(reference, rotation=False, scan_averaged=True)
        vibration_hz = estimator.learn_vibration(at_rest, line_time)
    measure = methods.make("semservo", reference, mask=mask, scan_averaged=settings.scan_averaged,
                           vibration_hz=vibration_hz, line_time_s=line_time)
    at_rest = [measure(frame) for frame in at_rest]
    at_rest = np.array([(m.dx, m.dy) for m in at_rest if m.ok])
    noise_px = float(np.sqrt(np.mean(np.var(at_rest, axis=0, ddof=1)))) if len(at_rest) > 2 else 0.03
    return Taught(reference, mask, (float(taught[0]), float(taught[1])), noise_px, lab.clock.t,
                  lab.world.sem.charge.copy(), lab.world.rng.bit_generator.state,
                  (float(resting[0]), float(resting[1])), vibration_hz, line_time)


def run_timed_trial(case: str, law: str, start_um: tuple[float, float], *, seed: int = 1, stage_model: str = "calibrated",
                    settings: TimedSettings = TimedSettings(), method: str = "semservo",
                    taught: Taught | None = None) -> dict:
    """One trial on a continuously scanning SEM (module docstring): teach at home, jog by
    ``start_um``, servo with ``law`` ("paper" or "position") until converged (then, with
    ``hold_s``, hold that long), the scene is lost, the law refuses, or the iteration
    limit or time budget. ``taught``: what :func:`teach` left in a lab of the same case
    and seed (else it teaches). Returns the outcome, the fresh frames used, the frames scanned in all and the
    simulated seconds to the frame convergence was decided on, the true final error (that
    frame's mean pose against the reference's, px) and the stage's (``stage_error_px``:
    where the sample rested then, the vibration left out), and the true error (px) at the
    end of every scan against simulated time (``trace``)."""
    lab = Lab(case, seed, stage_model=stage_model, phase_walk_rad_per_sqrt_s=settings.phase_walk_rad_per_sqrt_s)
    if taught is None:
        taught = teach(lab, settings)
    else:  # taught in another lab of the same seed: this one starts where teaching ended
        taught.start(lab)
    measure = taught.measure(method, settings.scan_averaged)
    controller = _law_for(law, stage_model, settings, taught.noise_px)
    taught_um = np.array(taught.taught_um)
    taught_resting_um = np.array(taught.resting_um if taught.resting_um is not None else taught.taught_um)
    converge_frames = settings.converge_frames
    lab.jog(*start_um)
    jitter = np.random.default_rng([seed, *(int(round(value * 1e3)) % 2**32 for value in start_um)])
    started = lab.clock.t + settings.start_after_s + jitter.uniform(0.0, settings.start_jitter_s)
    frame_time = lab.settings.frame_time_s
    line_time = lab.settings.line_time_s
    pixel_nm = lab.pixel_um * 1000

    towards = np.array(start_um) / max(float(np.hypot(*start_um)), 1e-12)
    overshoot = [0.0]

    true_vector = [np.zeros(2)]

    def true_error_px(interval) -> float:
        error = (lab.true_pose(interval) - taught_um) / lab.pixel_um
        true_vector[0] = error
        # Overshoot: how far the content went past the target, along the start's direction.
        overshoot[0] = max(overshoot[0], -float(error @ towards))
        return float(np.hypot(*error))

    def summary_at(interval, truth: float) -> dict:
        # Where the sample rested during that frame against where it rested while the
        # reference was scanned, the vibration left out of both: what a stage can be put at
        # (the frame's own mean pose also holds the vibration's mean over its scan, which no
        # stage move removes: up to ~0.05 px at x5000).
        resting = (lab.true_pose(interval, vibration=False) - taught_resting_um) / lab.pixel_um
        return {"fresh_frames": fresh_used, "frames_scanned": scanned, "seconds": interval[1] - started,
                "iterations": iterations, "true_error_px": truth, "stage_error_px": float(np.hypot(*resting))}

    trace, records, recent = [], [], []
    scanned = fresh_used = iterations = lost = corrections = 0
    settled_at, last_end, converged_at = -math.inf, None, None
    outcome, reason = "failed", f"iteration limit ({settings.max_iterations}) reached"
    hold_worst_px, t = 0.0, started
    final_interval = None
    while True:
        interval = (t, t + frame_time)
        t = interval[1]
        scanned += 1
        first_row = 0
        if interval[0] < settled_at:  # scanned while the last move landed: a pose in between
            first_row = rows_scanned_after(lab.settings.rows, interval[0], interval[1], settled_at)
            if not settings.partial_frames or method != "semservo" or first_row is None:
                trace.append((interval[1] - started, true_error_px(interval), False))
                continue
        frame, interval = lab.scan_at(interval[0])
        scan_time = interval[1] - interval[0]
        if first_row:  # the rows scanned after the move settled
            interval = (interval[0] + first_row * line_time, interval[1])
        fresh_used += 1
        truth = true_error_px(interval)
        trace.append((interval[1] - started, truth, True))
        if converged_at is not None:
            hold_worst_px = max(hold_worst_px, truth)
            if interval[1] - converged_at >= settings.hold_s:
                break
        measured = measure(frame, first_row) if first_row else measure(frame)
        record = {"t_s": interval[1] - started, "fresh": fresh_used, "scanned": scanned, "ok": measured.ok,
                  "first_row": first_row,
                  "true_error_px": truth, "true_stage_error_px": [float(value) for value in true_vector[0]]}
        if not measured.ok:
            lost += 1
            record["action"] = f"held: {measured.reason}"
            records.append(record)
            if lost >= settings.lost_after:
                outcome, reason = "failed", f"scene lost: {measured.reason}"
                break
            continue
        lost = 0
        error_px = math.hypot(measured.dx, measured.dy)
        recent = (recent + [(measured.dx, measured.dy)])[-converge_frames:]
        record.update(dx_px=measured.dx, dy_px=measured.dy, error_px=error_px)
        if controller.converged is None and converged_at is None and len(recent) == converge_frames \
                and math.hypot(*np.mean(recent, axis=0)) <= settings.tolerance_px:
            record["action"] = "within tolerance"
            records.append(record)
            outcome, reason, converged_at, final_interval = "converged", "", interval[1], interval
            summary = summary_at(interval, truth)
            if settings.hold_s <= 0:
                break
            continue
        if error_px > 0.45 * frame.shape[1]:
            record["action"] = "held: beyond the field"
            records.append(record)
            outcome, reason = "failed", f"measured {error_px:.0f} px: beyond half the field (lost or diverged)"
            break
        if converged_at is None and iterations >= settings.max_iterations:
            break
        if converged_at is None and settings.time_budget_s is not None and t - started > settings.time_budget_s:
            reason = f"time budget ({settings.time_budget_s:g} s) spent"
            break
        sampling = interval[1] - last_end if last_end is not None else 2 * frame_time
        last_end = interval[1]
        try:
            step = controller.step(measured.dx, measured.dy, 0.0, pixel_nm, sampling, frame_interval_s=interval,
                                   now_s=interval[1] + settings.latency_s, scan_time_s=scan_time)
        except UnexpectedResponse as error:
            outcome, reason = "failed", str(error)
            record["action"] = "held: unexpected response"
            records.append(record)
            break
        move, _ = saturate_planar(step.move, planar_limit_um(controller, settings.max_move_um, settings.max_moves))
        iterations += 1
        if controller.converged and converged_at is None:
            record["action"] = "within tolerance"
            records.append(record)
            outcome, reason, converged_at, final_interval = "converged", "", interval[1], interval
            summary = summary_at(interval, truth)
            if settings.hold_s <= 0:
                break
            continue
        if not move:
            record["action"] = "held: within tolerance" if controller.converged else "held: measuring again"
            controller.applied({})
            records.append(record)
            continue
        voltages, written_at, settled_at = lab.move_in_pieces(move, settings.max_move_um,
                                                              interval[1] + settings.latency_s)
        record.update(cost=step.cost, gain=step.gain, move=move, voltages=voltages[-1], pieces=len(voltages),
                      action="moved")
        controller.applied(move, at_s=written_at)
        if converged_at is not None:
            corrections += 1
        records.append(record)
    if converged_at is None:
        final_interval = (t - frame_time, t)
        summary = summary_at(final_interval, true_error_px(final_interval))
    result = {
        "case": case, "law": law, "method": method, "stage_model": stage_model, "start_um": list(start_um),
        "seed": seed, "outcome": outcome, "reason": reason, **summary, "overshoot_px": overshoot[0],
        "frame_time_s": frame_time, "pixel_um": lab.pixel_um, "settings": asdict(settings),
        "records": records, "trace": trace,
    }
    if settings.hold_s > 0 and converged_at is not None:
        result.update(hold_s=t - converged_at, hold_corrections=corrections, hold_worst_true_px=hold_worst_px)
    return result


def rmse_psnr(desired: np.ndarray, final: np.ndarray) -> tuple[float, float]:
    """RMSE and PSNR (dB) between the desired and the final image, 8-bit scale, as the
    paper's Table III (both levelled to the same range first)."""
    a = cv2.normalize(desired.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX)
    b = cv2.normalize(final.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX)
    rmse = float(np.sqrt(np.mean((a - b) ** 2)))
    return rmse, float(20 * math.log10(255.0 / max(rmse, 1e-9)))
