"""A positioning run as typed state, and the loop's steps as small functions over it.

Each motion estimate goes through the same steps, in order; every one is a function of
the run (and the estimate) that returns what it decided, so each is tested alone:

1. :func:`admit`: is the estimate against this run's reference? (one or two in flight
   from before a teach are let pass; a third in a row ends the run: taught again)
2. :func:`gate`: may it move the stage? The frames must carry a pixel size, and the
   estimate must be **fresh** (what it measured scanned wholly after the last move
   settled: a frame scanned during a move shows both positions; a partial frame, the
   rows after the move, is fresh) and **confident**.
3. :func:`law_step`: the law's step on the fresh, confident estimate (the paper's eq.
   30-37, or the position law's Kalman step, which also judges its own convergence).
   :func:`measure`: the error convergence is judged on (the mean of the last
   ``converge_frames`` fresh errors, or the position law's own verdict), and progress.
4. :func:`judge`: converged, out of iterations, or making no progress.
5. :func:`decide`: the law's move, saturated, unless the cost is diverging.
6. moving the stage is the core's (:class:`services.controller.core.ControllerCore`),
   which tells the law what was carried out (``applied``); then the iteration is recorded.

The tilts (alpha, beta) are measured once per focus sweep: :func:`tilt_step` acts on
each fresh sweep once, on the mean of the sweeps since the last tilt move, and only on
an error its sweeps can tell from zero (:data:`TILT_SIGNIFICANCE`).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass, field
from typing import Literal

import numpy as np

from semservo.control import (
    ControlLaw, LawStep, PositionLaw, PositionTiltLaw, TiltLaw, UnexpectedResponse, planar_limit_um, saturate_planar,
)
from semservo.estimation.tilt import foreshortening
from semservo.messages import MotionEstimate
from semservo.protocol.controller import RunSettings

#: Estimates in a row against another reference before the run fails (one or two may be
#: in flight from before the run's reference was taught).
FOREIGN_ESTIMATES_TO_FAIL = 3

#: Progress: an error this much below the best so far is progress.
PROGRESS_FACTOR = 0.9

#: A tilt run makes no progress only after this many focus sweeps without it too.
STALL_SWEEPS = 4

#: A tilt error within this many standard errors of zero (the mean of the sweeps since
#: the last tilt move) is not acted on: the sweeps cannot tell it from zero, and a move on
#: their noise only adds it to the pose (runs on hole_low_mag, measured to about +-0.1
#: degree, chased it until they stalled). The run sweeps again and pools instead.
TILT_SIGNIFICANCE = 2.0

#: While the tilts are held to pool sweeps (above), the run is deciding, not stalled: the
#: pool's standard error falls as 1 / sqrt(sweeps). Up to this many sweeps pooled (a
#: quarter of one sweep's error) before the stall rule may end the run.
DECIDING_SWEEPS = 16

Ending = Literal["converged", "failed", "stopped"]


@dataclass(slots=True)
class IterationRecord:
    """One estimate's iteration, as recorded (journal, events, the run's record). A
    field misspelt here fails at once (slots), not in a record read weeks later."""

    seq: int
    dx_px: float
    dy_px: float
    rotation_deg: float
    confidence: float
    snr_db: float
    pixel_size_nm: float | None
    frame_acquired_at_ns: int
    frame_published_at_ns: int
    estimate_published_at_ns: int
    frame_source_interval_s: tuple[float, float] | None  # of the rows measured (a partial frame's after the move)
    action: str = ""
    first_row: int = 0  # a partial frame's first row measured (0: the whole frame)
    rows_scanned_from_ns: int | None = None  # and when that row's scan began
    t_ns: int = 0
    iteration: int = 0
    error_px: float | None = None
    mean_error_px: float | None = None
    error: tuple[float, ...] | None = None
    cost: float | None = None
    gain: float | None = None
    velocity: tuple[float, ...] | None = None
    sampling_time_s: float | None = None
    move: dict[str, float] | None = None
    saturated: bool | None = None
    turn_deg: dict[str, float] | None = None
    targets: dict[str, float] | None = None  # the axes that made the move (the stage's, or the beam's)
    pieces: int | None = None  # commands the planar move was made in (moves_per_frame)
    pieces_written_at_ns: list[int] | None = None  # when each was written
    command_written_at_ns: int | None = None
    command_settled_at_ns: int | None = None
    voltages: dict[str, float] | None = None
    positions_um: dict[str, float] | None = None
    angles_deg: dict[str, float] | None = None
    latency_ms: float | None = None
    alpha_deg: float | None = None
    beta_deg: float | None = None
    tilt_confidence: float | None = None
    tilt_seq: int | None = None
    tilt_frames: int | None = None
    tilt_action: str | None = None
    tilt_error: tuple[float, ...] | None = None
    tilt_cost: float | None = None
    tilt_gain: float | None = None
    tilt_velocity: tuple[float, ...] | None = None
    tilt_sampling_time_s: float | None = None
    tilt_uncertainty_deg: tuple[float, ...] | None = None  # this sweep's standard errors (alpha, beta)
    tilt_pooled: int | None = None  # sweeps since the last tilt move the errors were averaged over
    tilt_mean_deg: dict[str, float] | None = None  # their mean: what the tilts were judged and moved on
    tilt_spread_deg: dict[str, float] | None = None  # its standard error
    # After a tilt move: the estimator cancelled the focus sweep in progress (its frames show
    # poses in between) and starts the next once the tilt has settled.
    tilt_sweeps_restarted: bool | None = None

    @classmethod
    def of(cls, estimate: MotionEstimate) -> "IterationRecord":
        return cls(seq=estimate.seq, dx_px=estimate.dx_px, dy_px=estimate.dy_px, rotation_deg=estimate.rotation_deg,
                   confidence=estimate.confidence, snr_db=estimate.snr_db, pixel_size_nm=estimate.pixel_size_nm,
                   frame_acquired_at_ns=estimate.frame_acquired_at_ns,
                   frame_published_at_ns=estimate.frame_published_at_ns,
                   estimate_published_at_ns=estimate.published_at_ns,
                   frame_source_interval_s=estimate.rows_source_interval_s or estimate.frame_source_interval_s,
                   first_row=estimate.first_row, rows_scanned_from_ns=estimate.rows_scanned_from_ns)

    def to_json(self) -> dict:
        """The record as JSON fields; a field never set is left out."""
        return {key: value for key, value in asdict(self).items()
                if value is not None or key in ("pixel_size_nm", "frame_source_interval_s")}


@dataclass
class Tilts:
    """The tilts' part of a run: they are measured once per focus sweep."""

    law: TiltLaw | PositionTiltLaw
    last_seq: int | None = None  # the last sweep looked at
    settled_ns: int = 0  # when the last tilt move has arrived: sweeps scanned before are stale
    within: dict[str, float] | None = None  # the last fresh sweep's errors, when within tolerance
    last_error: dict[str, float] | None = None  # the last fresh, confident sweep's errors
    last_end_s: float | None = None  # that sweep's end on the source's clock (its sampling time)
    moves: int = 0
    sweeps: int = 0  # fresh sweeps measured
    #: The fresh sweeps' errors since the last tilt move, with their standard errors
    #: (None where the estimator did not give them): what :meth:`pooled` averages.
    since_move: list[tuple[dict[str, float], dict[str, float] | None]] = field(default_factory=list)
    #: Whether the last sweep's error was held as not yet told from zero (pooling).
    holding: bool = False
    #: Fresh sweeps in a row that could not tell the tilts, and the last one's reason.
    refused_in_row: int = 0
    last_refusal: str = ""
    #: The foreshortening the estimator undid on the last frame (from the tilts it
    #: reported with it; :func:`foreshortening_changed`).
    undone: np.ndarray | None = None

    def deciding(self) -> bool:
        """Pooling sweeps to tell an error from zero, and not for too long yet
        (:data:`DECIDING_SWEEPS`): the stall rule waits."""
        return self.holding and len(self.since_move) < DECIDING_SWEEPS

    def moved(self, settled_ns: int) -> None:
        """A tilt move was commanded, arriving at ``settled_ns``: sweeps before it are stale."""
        self.settled_ns = settled_ns
        self.moves += 1
        self.since_move.clear()

    def pooled(self) -> tuple[dict[str, float], dict[str, float]]:
        """The errors of the sweeps since the last move, averaged with weights 1 / sigma^2,
        and the mean's standard error per DOF. Without standard errors for every sweep,
        the latest sweep alone with a standard error of 0 (it is taken as it is)."""
        latest = self.since_move[-1][0]
        if any(sigmas is None for _, sigmas in self.since_move):
            return dict(latest), {dof: 0.0 for dof in latest}
        mean, spread = {}, {}
        for dof in latest:
            weights = np.array([1.0 / max(sigmas[dof], 1e-6) ** 2 for _, sigmas in self.since_move])
            values = np.array([errors[dof] for errors, _ in self.since_move])
            mean[dof] = float(np.sum(weights * values) / np.sum(weights))
            spread[dof] = float(1.0 / np.sqrt(np.sum(weights)))
        return mean, spread


@dataclass
class Progress:
    """Whether the error still falls: the best normalized error (1 = at tolerance) and
    how many fresh estimates (and focus sweeps) have gone by since it was last beaten."""

    best: float = math.inf
    since_best: int = 0
    sweeps_since_best: int = 0

    def update(self, normalized_error: float, new_sweep: bool) -> None:
        if normalized_error <= 1.0 or normalized_error < PROGRESS_FACTOR * self.best:
            self.best = min(self.best, normalized_error)
            self.since_best = self.sweeps_since_best = 0
            return
        self.since_best += 1
        self.sweeps_since_best += int(new_sweep)


@dataclass
class Run:
    """One positioning run: what it was told, where it stands, what it has recorded."""

    id: str
    reference_id: str
    settings: RunSettings
    started_at_ns: int
    stage_at_start: dict
    law: ControlLaw | PositionLaw
    tilts: Tilts | None = None
    iterations: int = 0  # moves made
    records: list[dict] = field(default_factory=list)
    outcome: dict | None = None
    stage_log: list[dict] = field(default_factory=list)
    path: str | None = None
    # The loop's memory between estimates:
    last_command_ns: int = 0  # frames whose scan began before this show the stage moving
    last_source_end_s: float | None = None  # the last acted frame's end on the source's clock
    last_acted_acquired_ns: int | None = None
    low_confidence: int = 0  # in a row
    foreign: int = 0  # estimates in a row against another reference
    min_cost: float = math.inf
    rising: int = 0  # moves in a row with the cost above diverge_factor x its minimum
    held_stale: int = 0
    fresh_frames: int = 0  # fresh, confident estimates used
    partial_frames: int = 0  # of them, partial frames (the rows of a scan after a move settled)
    recent: deque = field(default_factory=deque)  # the last converge_frames fresh (dx, dy, rotation)
    progress: Progress = field(default_factory=Progress)
    beam: object | None = None  # the stage's beam shift (services.controller.split.BeamAxes), when a run may use it

    @property
    def dofs(self) -> list[str]:
        return list(self.settings.dofs)

    def to_record(self) -> dict:
        """The run's whole record (``runs/<id>.json``, the ``run`` command)."""
        return {"id": self.id, "reference_id": self.reference_id, "settings": self.settings.model_dump(),
                "started_at_ns": self.started_at_ns, "stage_at_start": self.stage_at_start,
                "iterations": self.iterations, "records": self.records, "outcome": self.outcome,
                "stage_log": self.stage_log, "min_cost": None if math.isinf(self.min_cost) else self.min_cost,
                "held_stale": self.held_stale, "fresh_frames": self.fresh_frames,
                "partial_frames": self.partial_frames, "path": self.path}

    def header(self) -> dict:
        """What a controller started after this one dies needs to finish the run."""
        return {"id": self.id, "reference_id": self.reference_id, "settings": self.settings.model_dump(),
                "started_at_ns": self.started_at_ns, "stage_at_start": self.stage_at_start}


@dataclass(frozen=True)
class Verdict:
    """What a step says of an estimate: record it with ``action`` (None: not recorded),
    and end the run as ``ending`` with ``reason`` when that is set."""

    action: str | None
    ending: Ending | None = None
    reason: str = ""


@dataclass(frozen=True)
class Measurement:
    """The errors of one fresh estimate as the run judges them."""

    error_px: float  # the fresh frame's whole translation error (px), servoed or not
    mean: tuple[float, float, float]  # mean translation size (px, the servoed axes), 0, mean turn size (degrees) of the recent fresh frames
    within: bool  # converged, if the run is not holding
    planar: bool = True  # the run servoes x or y (else no translation is judged)

    @property
    def mean_error_px(self) -> float | None:
        """The translation error as the run judges it (px, over the axes it servoes);
        None where it servoes neither x nor y."""
        return float(math.hypot(self.mean[0], self.mean[1])) if self.planar else None


@dataclass(frozen=True)
class Decision:
    """What to command: planar targets (um, relative) and turns (degrees, relative)."""

    step: LawStep  # the law's step, its planar move saturated
    targets: dict[str, float]
    turns: dict[str, float]
    saturated: bool  # the planar move was
    turn_saturated: bool  # a turn or tilt was
    diverging: str | None = None  # why the run must fail instead


# -- the steps ------------------------------------------------------------------------------
def admit(run: Run, estimate: MotionEstimate) -> Verdict | None:
    """None: the estimate is against the run's reference. Otherwise a verdict without a
    record: ignored (one or two may be in flight from before the reference was taught),
    or the run fails (the estimator now measures against another one)."""
    if estimate.reference_id == run.reference_id:
        run.foreign = 0
        return None
    run.foreign += 1
    if run.foreign >= FOREIGN_ESTIMATES_TO_FAIL:
        return Verdict(None, "failed", f"the reference changed during the run: the estimator now measures against "
                                       f"{estimate.reference_id}, not the run's {run.reference_id} (taught again?)")
    return Verdict(None)


def gate(run: Run, estimate: MotionEstimate) -> Verdict | None:
    """None when the estimate may move the stage; else why not (held, or the run ends)."""
    if estimate.pixel_size_nm is None:
        # Pixels cannot become micrometres: never guess the scale of a real stage's move.
        return Verdict("held: pixel size unknown", "failed",
                       "the frames carry no pixel size (their files or source do not say): set "
                       "SEMSERVO_IMAGESERVER__PIXEL_SIZE_NM (or the magnification) and start again")
    if seen_from_ns(estimate) < run.last_command_ns:
        run.held_stale += 1
        return Verdict("held: stale (scanned during the last move)")
    if estimate.confidence < run.settings.min_confidence:
        run.low_confidence += 1
        if run.low_confidence >= run.settings.lost_after:
            return Verdict("held: low confidence", "failed",
                           f"scene lost: {run.low_confidence} low-confidence frames in a row")
        return Verdict("held: low confidence")
    run.low_confidence = 0
    return None


def uses_partial_frames(settings: RunSettings) -> bool:
    """Whether a run acts on partial frames (the rows after a move): as its settings say,
    by default with the position law (the paper's velocity law gains nothing from more
    frequent frames: its displacement is its velocity times the sampling time)."""
    return settings.law == "position" if settings.partial_frames is None else settings.partial_frames


def seen_from_ns(estimate: MotionEstimate) -> int:
    """When the scan of what the estimate measured began: the frame's, or a partial
    frame's first measured row's (its rows after a move settled)."""
    return estimate.rows_scanned_from_ns or estimate.frame_scan_started_at_ns or estimate.frame_acquired_at_ns


def servoed_planar_px(dofs, dx_px: float, dy_px: float) -> float:
    """The translation error along the planar axes a run servoes (px): x, y or both; 0
    where it servoes neither."""
    return math.hypot(dx_px if "x" in dofs else 0.0, dy_px if "y" in dofs else 0.0)


def servoes_planar(dofs) -> bool:
    return "x" in dofs or "y" in dofs


def within_tolerance(run: Run, dx_px: float, dy_px: float, rotation_deg: float) -> bool:
    """The translation error along the servoed planar axes, the turn when rotation is
    servoed, and the last fresh tilts when they are, under tolerance."""
    settings, dofs = run.settings, run.settings.dofs
    within = servoed_planar_px(dofs, dx_px, dy_px) <= settings.tolerance_px \
        and ("rotation" not in dofs or abs(rotation_deg) <= settings.tolerance_deg)
    if within and run.tilts is not None:
        within = run.tilts.within is not None and all(
            abs(run.tilts.within[dof]) <= settings.tolerance_tilt_deg for dof in run.tilts.law.dofs)
    return within


def normalized_error(run: Run, mean: tuple[float, float, float]) -> float:
    """The largest error over the run's DOFs in units of its tolerance (1: at tolerance);
    the tilts count once a sweep has measured them."""
    settings, dofs = run.settings, run.settings.dofs
    parts = [0.0]
    if servoes_planar(dofs):
        parts.append(math.hypot(mean[0], mean[1]) / settings.tolerance_px)
    if "rotation" in dofs:
        parts.append(abs(mean[2]) / settings.tolerance_deg)
    if run.tilts is not None:
        last = run.tilts.last_error
        parts.append(math.inf if last is None else max(abs(value) for value in last.values())
                     / settings.tolerance_tilt_deg)
    return max(parts)


def law_judges_convergence(run: Run) -> bool:
    """Whether the run's planar law says itself when the target is reached (the position
    law: ``converged`` is a bool; the paper's law leaves it to :func:`measure`'s mean)."""
    return run.law.converged is not None and bool(run.law.dofs)


def measure(run: Run, estimate: MotionEstimate, *, new_sweep: bool = False) -> Measurement:
    """The fresh estimate's errors: convergence is judged on the mean of the last
    ``converge_frames`` errors' sizes (the mean, not each one, so estimation noise or
    vibration near the tolerance cannot keep a finished run going; ``converge_on="each"``
    asks it of each). The mean of the sizes, not the size of the mean: errors either side
    of the target, a run overshooting across moves, do not cancel (averaging the vectors
    once stopped runs 0.4-0.55 px away by their own last estimate: (+0.37, -0.31),
    (-0.07, +0.10), (-0.37, +0.41) px average to 0.07 px)."""
    settings = run.settings
    run.fresh_frames += 1
    run.partial_frames += bool(estimate.first_row)
    run.recent.append((estimate.dx_px, estimate.dy_px, estimate.rotation_deg))
    while len(run.recent) > settings.converge_frames:
        run.recent.popleft()
    # The sizes along the servoed axes only: an axis the run leaves alone is not judged
    # (a turn-only run's view may stay far off in x, y).
    sizes = [(servoed_planar_px(settings.dofs, dx, dy), abs(rotation)) for dx, dy, rotation in run.recent]
    mean_size, mean_turn = (float(value) for value in np.mean(sizes, axis=0))
    mean = (mean_size, 0.0, mean_turn)  # sizes: a translation's along x, the turn's magnitude
    within = len(run.recent) == settings.converge_frames and within_tolerance(run, *mean)
    if settings.converge_on == "each":
        within = within and all(within_tolerance(run, *error) for error in run.recent)
    if law_judges_convergence(run):
        # The position law judges its own: the error it predicts for now, one standard
        # deviation added, within tolerance (the last frames measured poses left behind);
        # its estimate is the error the run reports (status, records).
        within = run.law.converged and within_tolerance(run, 0.0, 0.0, 0.0)
        estimated, turn = run.law.planar_estimate()[0], run.law.turn_estimate()[0]
        if math.isfinite(estimated) or math.isfinite(turn):
            mean = (estimated if math.isfinite(estimated) else mean_size, 0.0,
                    turn if math.isfinite(turn) else mean_turn)
    if run.tilts is None or run.tilts.last_error is not None:
        run.progress.update(normalized_error(run, mean), new_sweep)
    return Measurement(math.hypot(estimate.dx_px, estimate.dy_px), mean, within, servoes_planar(settings.dofs))


def judge(run: Run, measurement: Measurement) -> Verdict | None:
    """Converged, out of iterations, the tilts lost, or no longer making progress; None: go on."""
    settings = run.settings
    if measurement.within and not settings.hold:
        return Verdict("within tolerance", "converged", converged_reason(run, measurement))
    if run.iterations >= settings.max_iterations:
        return Verdict(None, "failed", f"iteration limit ({settings.max_iterations}) reached")
    if run.tilts is not None and run.tilts.refused_in_row >= settings.tilts_lost_after:
        # Not the iteration limit hundreds of frames later: the tilts cannot be servoed
        # on sweeps that cannot tell them, and the operator needs to know why.
        return Verdict("held: tilts lost", "failed",
                       f"tilts lost: {run.tilts.refused_in_row} focus sweeps in a row could not tell them "
                       f"({run.tilts.last_refusal})")
    progress = run.progress
    if progress.since_best >= settings.stall_after and (
            run.tilts is None or (progress.sweeps_since_best >= STALL_SWEEPS and not run.tilts.deciding())):
        return Verdict("held: no progress", "failed", stall_reason(run, measurement))
    return None


def converged_reason(run: Run, measurement: Measurement) -> str:
    """What a converged run judged, in its own words: for the planar axes it servoes
    (named when only one) the position law's estimate or the paper's law's mean over its
    last fresh frames, the turn and the tilts where they are servoed, and the planar
    axes it left alone with how far the view is off along them (never an error of 0 for
    an axis nobody measured)."""
    settings, dofs = run.settings, run.settings.dofs
    planar_axes = [axis for axis in ("x", "y") if axis in dofs]
    named = "" if len(planar_axes) != 1 else f" in {planar_axes[0]}"
    said = []
    if planar_axes and law_judges_convergence(run):
        error, spread = run.law.planar_estimate()
        said.append(f"the position law's estimate {error:.3f} px{named} (one standard deviation {spread:.3f} px) "
                    f"within {settings.tolerance_px:g} px, from {run.fresh_frames} fresh frames")
    elif planar_axes:
        said.append(f"mean error of the last {len(run.recent)} fresh frames {measurement.mean_error_px:.3f} px{named}, "
                    f"under {settings.tolerance_px:g} px")
    turn, spread = run.law.turn_estimate() if law_judges_convergence(run) else (math.nan, math.nan)
    if "rotation" in dofs and math.isfinite(turn):
        said.append(f"the position law's turn {turn:.3f} deg (one standard deviation {spread:.3f} deg) within "
                    f"{settings.tolerance_deg:g} deg")
    elif "rotation" in dofs:
        said.append(f"the turn's mean error over the last {len(run.recent)} fresh frames "
                    f"{measurement.mean[2]:.3f} deg, "
                    f"under {settings.tolerance_deg:g} deg")
    if run.tilts is not None and run.tilts.within:
        said.append("tilts " + ", ".join(f"{dof} {value:+.3f}" for dof, value in run.tilts.within.items())
                    + f" deg, within {settings.tolerance_tilt_deg:g} deg")
    left = [axis for axis in ("x", "y") if axis not in dofs]
    if left and run.recent:
        dx, dy, _ = run.recent[-1]
        off = {"x": dx, "y": dy}
        said.append(f"not servoed: {', '.join(left)} (the view is "
                    + ", ".join(f"{off[axis]:+.2f} px in {axis}" for axis in left) + " off)")
    return "; ".join(said)


def stall_reason(run: Run, measurement: Measurement) -> str:
    """Why a run that makes no progress is stopped, in the words an operator needs."""
    settings = run.settings
    what = [f"the error has not fallen below {PROGRESS_FACTOR:g} x its best for {run.progress.since_best} fresh "
            f"frames"]
    if measurement.mean_error_px is not None:
        what.append(f"translation {measurement.mean_error_px:.3f} px (tolerance {settings.tolerance_px:g})")
    if run.tilts is not None and run.tilts.last_error:
        what.append("tilts " + ", ".join(f"{dof} {value:+.3f} deg" for dof, value in run.tilts.last_error.items())
                    + f" (tolerance {settings.tolerance_tilt_deg:g})")
    return ("no progress: " + "; ".join(what) + ". Vibration or noise above the tolerance, a DOF the instrument "
            "cannot measure well at these settings, or a stage that does not follow its commands")


def sampling_time(run: Run, estimate: MotionEstimate) -> float:
    """The measured time between this iteration and the last (eq. 37), on the image
    source's clock when it has one (the fake lab's simulated time), else the frames'
    acquisition times. The first iteration takes two scan durations: a fresh frame
    comes every second scan."""
    interval = estimate.rows_source_interval_s or estimate.frame_source_interval_s
    end_s = interval[1] if interval else None
    if end_s is not None and run.last_source_end_s is not None:
        return max(end_s - run.last_source_end_s, 1e-3)
    if end_s is None and run.last_acted_acquired_ns:
        return max((estimate.frame_acquired_at_ns - run.last_acted_acquired_ns) / 1e9, 1e-3)
    if interval:
        return max(2 * (interval[1] - interval[0]), 1e-3)
    return 0.5


def law_step(run: Run, estimate: MotionEstimate, sampling_time_s: float, now_ns: int) -> LawStep | Verdict:
    """The planar law's step on a fresh, confident estimate (``gate`` let it through).
    Either law is called the same way; the position law uses the frame's scan interval
    and the time the move will be written (wall clock, as the stage's ``settled_at_ns``)
    to follow the drift. A stage that did not move the content as commanded, twice in a
    row, ends the run (:class:`~semservo.control.UnexpectedResponse`)."""
    if not run.law.dofs:
        return LawStep.idle()
    started_ns = estimate.frame_scan_started_at_ns or estimate.frame_acquired_at_ns
    scan_time_s = (estimate.frame_acquired_at_ns - started_ns) / 1e9 if estimate.first_row else None
    try:
        return run.law.step(estimate.dx_px, estimate.dy_px, estimate.rotation_deg, estimate.pixel_size_nm,
                            sampling_time_s, fresh=True, confident=True,
                            frame_interval_s=(seen_from_ns(estimate) / 1e9, estimate.frame_acquired_at_ns / 1e9),
                            now_s=now_ns / 1e9, scan_time_s=scan_time_s)
    except UnexpectedResponse as error:
        return Verdict("held: unexpected response", "failed", f"the stage did not move as commanded: {error}")


def decide(run: Run, step: LawStep, tilt_step: LawStep | None) -> Decision:
    """The move to command from the law's step (and the tilts'), saturated at
    ``max_move_um`` (the position law: ``moves_per_frame`` x ``max_move_um``, made in
    pieces of at most ``max_move_um``) and ``max_turn_deg``; ``diverging`` says why not to make it: the cost
    has stayed above ``diverge_factor`` x its minimum for ``diverge_iterations`` moves.
    Divergence is never judged against less than the square of ``diverge_floor_px`` (or
    of 5 x tolerance): near the target the cost is estimation noise and vibration,
    whatever tolerance the run asks for."""
    settings = run.settings
    move, saturated = saturate_planar(step.move, planar_limit_um(run.law, settings.max_move_um,
                                                                 settings.moves_per_frame))
    targets = {axis: move[f"{axis}_um"] for axis in ("x", "y") if f"{axis}_um" in move}
    turns = {axis: move[axis] for axis in ("rotation_deg",) if axis in move}
    if tilt_step is not None:
        turns.update(tilt_step.move)
    turn_saturated = False
    for axis, value in turns.items():
        if abs(value) > settings.max_turn_deg:
            turns[axis] = math.copysign(settings.max_turn_deg, value)
            turn_saturated = True
    run.min_cost = min(run.min_cost, step.cost)
    floor = max(5 * settings.tolerance_px, settings.diverge_floor_px) ** 2
    run.rising = run.rising + 1 if step.cost > settings.diverge_factor * max(run.min_cost, floor) else 0
    diverging = (f"diverging: cost above {settings.diverge_factor:g}x its minimum for {run.rising} moves"
                 if run.rising >= settings.diverge_iterations else None)
    return Decision(LawStep(step.error, step.cost, step.gain, step.velocity, move, step.integral, step.held), targets, turns,
                    saturated, turn_saturated, diverging)


#: A change of the foreshortening the estimator undoes (any entry of the matrix A of
#: :func:`semservo.estimation.tilt.foreshortening`) beyond this fraction of the rotation
#: tolerance (as radians) restarts the position law's estimate (:func:`foreshortening_changed`).
FORESHORTENING_CHANGE = 0.25


def foreshortening_changed(run: Run, estimate: MotionEstimate) -> bool:
    """Whether the estimator undid another foreshortening on this frame than on the one
    before, enough to move the turn it reads (a run servoing the rotation and the tilts).

    The estimator undoes the foreshortening of the tilts its last sweep measured; after a
    tilt move the frames until the next sweep are undone with the tilts before it, and
    the turn they read is off by as much as the change (a 5-DOF run on a real scene read
    -0.002 degree of turn until the sweep after a 1.7, 2.9 degree tilt move, then -0.08,
    the truth; the position law, sure of the earlier frames, took the jump for noise
    and the run converged 0.08 degree off). When the basis changes, what the law has
    learned of the position no longer holds: the caller restarts it (``view_moved``).
    A restart is not tied to a tilt move: with a DOF held at several degrees of tilt,
    sweeps that differ by their noise may restart it too, once per sweep at most (the
    cost: the position re-measured from the next frame)."""
    if run.tilts is None or "rotation" not in run.settings.dofs:
        return False
    if (estimate.alpha_deg is None or estimate.beta_deg is None) and run.tilts.undone is not None:
        return False  # a sweep that could not tell the tilts: the estimator undoes the last ones that could
    undone = foreshortening(estimate.alpha_deg, estimate.beta_deg)
    previous, run.tilts.undone = run.tilts.undone, undone
    if previous is None:
        return False
    return float(np.abs(undone - previous).max()) > FORESHORTENING_CHANGE * math.radians(run.settings.tolerance_deg)


def tilt_step(run: Run, estimate: MotionEstimate, record: IterationRecord) -> LawStep | None:
    """The tilts' part of an iteration: acted on once per focus sweep, and only for a
    sweep scanned after the last tilt move had arrived, on the mean of the sweeps since
    that move (:meth:`Tilts.pooled`). Held within half the tolerance, or within
    :data:`TILT_SIGNIFICANCE` standard errors of that mean (the sweeps cannot tell the
    error from zero: the next sweep is pooled), or when the sweep could not tell the
    tilts; the run may converge on a mean within tolerance."""
    tilts, settings = run.tilts, run.settings
    record.alpha_deg, record.beta_deg = estimate.alpha_deg, estimate.beta_deg
    record.tilt_confidence, record.tilt_seq = estimate.tilt_confidence, estimate.tilt_seq
    started = estimate.tilt_scan_started_at_ns
    if estimate.tilt_seq is None or estimate.tilt_seq == tilts.last_seq or started is None:
        return None
    tilts.last_seq = estimate.tilt_seq
    if started < tilts.settled_ns:
        record.tilt_action = "held: sweep scanned during the last tilt move"
        return None
    if estimate.alpha_deg is None or estimate.beta_deg is None \
            or (estimate.tilt_confidence or 0.0) < settings.min_tilt_confidence:
        record.tilt_action = "held: tilts not measured with confidence"
        tilts.refused_in_row += 1
        tilts.last_refusal = estimate.tilt_reason or f"confidence {estimate.tilt_confidence or 0.0:.2f}"
        return None
    tilts.refused_in_row = 0
    tilts.sweeps += 1
    errors = {"alpha": estimate.alpha_deg, "beta": estimate.beta_deg}
    record.tilt_frames, record.tilt_uncertainty_deg = estimate.tilt_frames, estimate.tilt_uncertainty_deg
    sigmas = dict(zip(("alpha", "beta"), estimate.tilt_uncertainty_deg)) if estimate.tilt_uncertainty_deg else None
    tilts.since_move.append(({dof: errors[dof] for dof in tilts.law.dofs},
                             {dof: sigmas[dof] for dof in tilts.law.dofs} if sigmas else None))
    mean, spread = tilts.pooled()
    record.tilt_pooled, record.tilt_mean_deg, record.tilt_spread_deg = len(tilts.since_move), mean, spread
    tilts.last_error = mean
    largest = max(abs(value) for value in mean.values())
    # Within tolerance, the run may converge on this mean; the tilts are still corrected
    # down to half the tolerance, or the run would end at its edge, but never on an
    # error its sweeps cannot tell from zero.
    tilts.within = dict(mean) if largest <= settings.tolerance_tilt_deg else None
    tilts.holding = False
    if largest <= settings.tolerance_tilt_deg / 2:
        record.tilt_action = "within tolerance"
        return None
    if all(abs(mean[dof]) <= TILT_SIGNIFICANCE * spread[dof] for dof in mean):
        record.tilt_action = (f"held: within {TILT_SIGNIFICANCE:g} standard errors of zero "
                              f"({len(tilts.since_move)} sweeps pooled)")
        tilts.holding = largest > settings.tolerance_tilt_deg  # beyond tolerance: still to be decided
        return None
    interval = estimate.tilt_source_interval_s
    end_s = interval[1] if interval else None
    if end_s is not None and tilts.last_end_s is not None:
        elapsed = max(end_s - tilts.last_end_s, 1e-3)
    elif interval:
        elapsed = max(2 * (interval[1] - interval[0]), 1e-3)
    else:
        elapsed = max(estimate.tilt_sweep_s or 1.0, 1e-3)
    tilts.last_end_s = end_s
    step = tilts.law.step(mean.get("alpha", estimate.alpha_deg), mean.get("beta", estimate.beta_deg), elapsed,
                          spread_deg=spread)
    record.tilt_error, record.tilt_cost, record.tilt_gain = step.error, step.cost, step.gain
    record.tilt_velocity, record.tilt_sampling_time_s, record.tilt_action = step.velocity, elapsed, "moved"
    return step
