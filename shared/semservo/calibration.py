"""Stage calibration from images: sweep one axis's voltage up and down, measure where the
stage went from the SEM images, and fit the displacement-voltage model (paper section
II-E: "these displacements are mapped to the respective channel voltages using our
displacement-voltage model"; the lab's model is fourth-order polynomials, one per
hysteresis branch, see ``shared/reference/nv403-and-tritor.md``).

The motion is measured by the same Fourier registration the servo loop uses
(:class:`semservo.estimation.MotionEstimator`, eq. 18-24), frame against a *key frame*:
the key frame is replaced when the content has moved ``keyframe_px`` from it, so a stroke
longer than the field of view is measured in overlapping pieces and the error grows
with the number of key frames (a few), not with the number of steps.

The pure parts (:func:`sweep_voltages`, :func:`fit_branches`, :func:`loop_width`) work
on arrays; :class:`Calibrator` runs a sweep through two small ports (the stage service
and a frame source) so it is tested on the simulated lab with no mocks and drives a
real stage the same way.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from semservo.control import CameraToStage
from semservo.estimation import MotionEstimator
from semservo.protocol import Port
from semservo.protocol import stage as stage_protocol
from semservo.stage_model import BranchModel
from semservo.wire import Frame

#: The lab fitted its polynomials to this order (V = p1 d^4 + ... + p5).
MODEL_ORDER = 4
#: A fit whose residual exceeds this share of the stroke is no model (the lab's loop fits
#: to well under 1 %; a sweep whose frames lagged their moves read 87 um over a 6.7 um stroke).
MAX_RESIDUAL_SHARE = 0.05


class CalibrationError(RuntimeError):
    """The sweep could not be measured (scene lost, no frames, a refused move)."""


@dataclass(frozen=True)
class SweepPoint:
    """One step of the sweep: the voltage set, the direction of the move that reached it
    (+1 rising, -1 falling), and where the images say the stage is."""

    voltage: float
    direction: int
    displacement_um: float  # along the calibrated axis, from the first rising point
    cross_um: float  # along the other axis (should stay near zero: cross-talk, drift)
    confidence: float
    frame_seq: int
    true_displacement_um: float | None = None  # from the simulator, when there is one


def sweep_voltages(low_v: float, high_v: float, step_v: float) -> list[tuple[float, int]]:
    """The voltages of one hysteresis cycle, ``low_v`` up to ``high_v`` and back, with
    the direction of the move that reaches each (the first point counts as rising: the
    sweep starts after coming down to ``low_v``, which relaxes the loop)."""
    if not high_v > low_v:
        raise ValueError(f"the sweep needs high_v > low_v, got {low_v} .. {high_v}")
    if not 0 < step_v <= high_v - low_v:
        raise ValueError(f"step_v must be in (0, {high_v - low_v}], got {step_v}")
    count = int(np.ceil((high_v - low_v) / step_v))
    rising = np.linspace(low_v, high_v, count + 1)
    return [(float(v), 1) for v in rising] + [(float(v), -1) for v in rising[-2::-1]]


def _branches(points: list[SweepPoint], attribute: str) -> tuple[dict[float, float], dict[float, float]]:
    rising = {p.voltage: getattr(p, attribute) for p in points if p.direction > 0}
    falling = {p.voltage: getattr(p, attribute) for p in points if p.direction < 0}
    # The turning point belongs to both branches: the falling branch starts there.
    top = max(rising)
    falling.setdefault(top, rising[top])
    return rising, falling


def fit_branches(points: list[SweepPoint], order: int = MODEL_ORDER, attribute: str = "displacement_um") -> BranchModel:
    """Least-squares polynomials V = p(d) for the rising and the falling branch (the
    form of the lab's model), d measured from the first rising point."""
    rising, falling = _branches(points, attribute)
    if min(len(rising), len(falling)) <= order:
        raise ValueError(f"a branch needs more than {order} points to fit order {order}")

    def fit(branch: dict[float, float]) -> tuple[float, ...]:
        displacements = np.array(list(branch.values()))
        voltages = np.array(list(branch.keys()))
        return tuple(float(c) for c in np.polyfit(displacements, voltages, order))

    return BranchModel(fit(rising), fit(falling))


def loop_width(points: list[SweepPoint], attribute: str = "displacement_um") -> float:
    """The hysteresis: the largest gap between the falling and the rising branch at the
    same voltage, as a fraction of the stroke (the sources quote 10-15 % at full
    range)."""
    rising, falling = _branches(points, attribute)
    common = sorted(set(rising) & set(falling))
    gaps = [falling[v] - rising[v] for v in common]
    stroke = max(rising.values()) - min(rising.values())
    if stroke <= 0:
        raise ValueError("the stage did not move: no stroke to compare the loop with")
    return float(max(gaps) / stroke)


def fit_residual_um(model: BranchModel, points: list[SweepPoint]) -> float:
    """RMS distance (um) between the measured points and the fitted branches, taken
    along the displacement (through each branch's inverse)."""
    errors = []
    for direction, branch in ((1, model.increasing), (-1, model.decreasing)):
        probe = BranchModel(branch, branch)
        for point in points:
            if point.direction == direction:
                errors.append(probe.position_for(point.voltage) - point.displacement_um)
    return float(np.sqrt(np.mean(np.square(errors))))


@dataclass
class CalibrationResult:
    axis: str
    points: list[SweepPoint]
    model: BranchModel
    loop_width: float
    residual_um: float
    stroke_um: float
    true_loop_width: float | None = None
    true_error_um: dict | None = None  # mean and max |measured - true| when simulated

    def summary(self) -> dict:
        summary = {
            "axis": self.axis, "points": len(self.points), "stroke_um": round(self.stroke_um, 3),
            "loop_width_percent": round(100 * self.loop_width, 2), "fit_residual_um": round(self.residual_um, 4),
            "increasing": list(self.model.increasing), "decreasing": list(self.model.decreasing),
        }
        if self.true_loop_width is not None:
            summary["true_loop_width_percent"] = round(100 * self.true_loop_width, 2)
            summary["true_error_um"] = self.true_error_um
        return summary

    def fit_problem(self) -> str | None:
        """Why the fit cannot be trusted as a model, or None: a residual over
        :data:`MAX_RESIDUAL_SHARE` of the stroke means the frames did not measure the steps
        (frames scanned before their move, a scene lost between key frames)."""
        if self.stroke_um <= 0 or self.residual_um > MAX_RESIDUAL_SHARE * self.stroke_um:
            return (f"the fit's residual ({self.residual_um * 1000:.0f} nm) is over {MAX_RESIDUAL_SHARE:.0%} of the "
                    f"stroke ({self.stroke_um:.3f} um): the frames did not measure the steps (frames scanned before "
                    "their move, or a scene lost between key frames)")
        return None

    def save(self, path: str | Path) -> Path:
        """The model as :func:`semservo.stage_model.load_model` reads it, with the sweep
        kept beside it (``calibration``) so a fit can be checked or redone later."""
        path = Path(path)
        document = {**self.model.to_dict(), "calibration": {
            **self.summary(), "created_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "sweep": [dataclasses.asdict(point) for point in self.points]}}
        path.write_text(json.dumps(document, indent=2))
        return path

    def plot(self, path: str | Path) -> Path:
        """The measured loop with the fitted branches (and the truth when simulated)."""
        import matplotlib

        matplotlib.use("Agg")
        from matplotlib import pyplot

        figure, axes = pyplot.subplots(figsize=(6.4, 4.8), dpi=100)
        for direction, colour, label, branch in ((1, "tab:red", "rising", self.model.increasing),
                                                 (-1, "tab:blue", "falling", self.model.decreasing)):
            chosen = [p for p in self.points if p.direction == direction]
            axes.plot([p.voltage for p in chosen], [p.displacement_um for p in chosen], "o", color=colour,
                      markersize=3, label=f"{label}, measured from images")
            if chosen[0].true_displacement_um is not None:
                axes.plot([p.voltage for p in chosen], [p.true_displacement_um for p in chosen], "x",
                          color="black", markersize=3, label="simulator truth" if direction > 0 else None)
            displacements = np.linspace(min(p.displacement_um for p in self.points),
                                        max(p.displacement_um for p in self.points), 200)
            axes.plot(np.polyval(branch, displacements), displacements, "-", color=colour, linewidth=1,
                      label=f"{label}, fitted order {len(branch) - 1}")
        axes.set_xlabel("voltage (V)")
        axes.set_ylabel(f"{self.axis} displacement (um)")
        axes.set_title(f"axis {self.axis}: loop {100 * self.loop_width:.1f} % of {self.stroke_um:.1f} um, "
                       f"fit RMS {self.residual_um * 1000:.0f} nm")
        axes.grid(alpha=0.3)
        axes.legend(fontsize=8)
        figure.tight_layout()
        path = Path(path)
        figure.savefig(path)
        pyplot.close(figure)
        return path


@dataclass
class Calibrator:
    """Sweeps one axis through the stage service and measures each step in the images.

    ``stage``: a port onto the stage service (:class:`semservo.protocol.Port`: ``state``,
    ``set_voltages``), over its socket or in process.
    ``next_frame``: ``next_frame(after_ns)`` returns the first frame whose scan started
    after ``after_ns`` (``time.time_ns`` clock), or raises :class:`CalibrationError`.
    ``truth``: optional, ``truth(frame)`` gives the true displacement of the axis (um)
    while the frame was scanned (the simulator knows it), or None where it cannot tell.
    ``started_v`` and ``last_v``: where the axis was before the sweep and the last voltage
    set, for a caller to say where a failed sweep left it.
    """

    stage: Port
    next_frame: Callable[[int], Frame]
    axis: str = "x"
    camera: CameraToStage = field(default_factory=CameraToStage)
    settle_s: float = 0.3
    keyframe_px: float = 32.0
    min_confidence: float = 0.3
    truth: Callable[[Frame], float] | None = None
    progress: Callable[[SweepPoint, int, int], None] | None = None
    started_v: float | None = None
    last_v: float | None = None

    def _set(self, voltage: float) -> int:
        self.stage.call(stage_protocol.SET_VOLTAGES, voltages={self.axis: voltage}, owner="calibrate")
        self.last_v = voltage
        return time.time_ns()

    def _approach(self, target_v: float, step_v: float) -> None:
        """Walk to the sweep's start in steps the stage's step and rate limits allow."""
        voltage = float(self.stage.call(stage_protocol.STATE).voltages[self.axis])
        self.started_v = self.last_v = voltage
        while abs(target_v - voltage) > 1e-9:
            voltage += float(np.clip(target_v - voltage, -step_v, step_v))
            self._set(voltage)
            time.sleep(self.settle_s)

    def _moved_um(self, content_dx: float, content_dy: float, pixel_size_nm: float) -> tuple[float, float]:
        stage_x, stage_y = self.camera.stage_move_um(content_dx, content_dy, pixel_size_nm)
        return (stage_x, stage_y) if self.axis == "x" else (stage_y, stage_x)

    def run(self, low_v: float, high_v: float, step_v: float) -> CalibrationResult:
        sweep = sweep_voltages(low_v, high_v, step_v)
        self._approach(low_v, step_v)
        points: list[SweepPoint] = []
        keyframe = keyframe_offset = None
        origin_true = None
        for index, (voltage, direction) in enumerate(sweep):
            frame = self.next_frame(self._set(voltage) + int(self.settle_s * 1e9))
            pixels = frame.pixels
            if keyframe is None:
                keyframe, keyframe_offset = MotionEstimator(pixels, rotation=False), np.zeros(2)
                motion_px, confidence = np.zeros(2), 1.0
            else:
                motion = keyframe.estimate(pixels)
                if motion.confidence < self.min_confidence:
                    raise CalibrationError(
                        f"lost the scene at {voltage:.2f} V (confidence {motion.confidence:.2f} < "
                        f"{self.min_confidence}): lower the magnification or the step")
                motion_px, confidence = np.array([motion.dx, motion.dy]), motion.confidence
            content = keyframe_offset + motion_px
            if np.hypot(*motion_px) > self.keyframe_px:
                keyframe, keyframe_offset = MotionEstimator(pixels, rotation=False), content
            if frame.header.pixel_size_nm is None:
                raise CalibrationError("the frames carry no pixel size, so image motion cannot be measured in "
                                       "micrometres: set SEMSERVO_IMAGESERVER__PIXEL_SIZE_NM")
            along, across = self._moved_um(content[0], content[1], frame.header.pixel_size_nm)
            true = self.truth(frame) if self.truth is not None else None
            if true is not None:
                origin_true = true if origin_true is None else origin_true
                true -= origin_true
            point = SweepPoint(voltage, direction, along, across, confidence, frame.header.seq, true)
            points.append(point)
            if self.progress is not None:
                self.progress(point, index + 1, len(sweep))
        return self.result(points)

    def result(self, points: list[SweepPoint]) -> CalibrationResult:
        model = fit_branches(points)
        measured = np.array([p.displacement_um for p in points])
        result = CalibrationResult(self.axis, points, model, loop_width(points), fit_residual_um(model, points),
                                   float(measured.max() - measured.min()))
        if all(point.true_displacement_um is not None for point in points):
            errors = np.abs(measured - np.array([p.true_displacement_um for p in points]))
            result.true_loop_width = loop_width(points, "true_displacement_um")
            result.true_error_um = {"mean": round(float(errors.mean()), 4), "max": round(float(errors.max()), 4)}
        return result
