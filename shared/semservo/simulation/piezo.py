"""A piezo stage axis driven open loop: voltage -> displacement with hysteresis,
creep and first-order settling, calibrated on the lab's measured TRITOR polynomials
(``shared/reference/nv403-and-tritor.md``).

Hysteresis is rate-independent, a generalized Prandtl-Ishlinskii model: displacement is
the mean of the lab's two measured branches, m(V), plus g(V) * mean_r (play_r(V) - V) / r̄
over play operators with backlash r spread uniformly over [0, 25] V, where g(V) is the
branches' measured half-gap at V. On a long excursion every operator follows the
voltage, so the curve runs on the measured branch (m +- g); after a reversal only
operators with r below half the excursion switch, so small moves show loops of a few
percent of the move (and the stuck operators give the lower small-signal gain real
piezos have). On top: after each
step the axis settles with time constant ``settle_s`` and creeps by
``creep_per_decade`` of the step per decade of time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from semservo import nv40

__all__ = ["Branch", "Hysteresis", "PiezoAxis", "voltage_for"]

#: V = p1 d^4 + p2 d^3 + p3 d^2 + p4 d + p5 (d in um), the lab's measured model.
TRITOR_POLYNOMIALS = {
    ("x", "increasing"): (-5.3343e-7, 1.7528e-4, -0.017184, 1.6457, -19.018),
    ("y", "increasing"): (-5.6939e-7, 1.8878e-4, -0.020198, 1.8527, -19.171),
    ("x", "decreasing"): (2.6118e-7, -2.2086e-5, 0.0032187, 0.73526, -21.086),
    ("y", "decreasing"): (4.9101e-7, -7.3072e-5, 0.0056593, 0.77264, -22.073),
}
STROKE_UM = 100.0
RESOLUTION_UM = 0.0002  # 0.2 nm


def voltage_for(axis: str, branch: str, displacement_um):
    """The lab's model: the voltage that gives ``displacement_um`` on a branch."""
    return np.polyval(TRITOR_POLYNOMIALS[(axis, branch)], displacement_um)


@dataclass
class Branch:
    """Displacement as a function of voltage on one measured branch (inverted once)."""

    voltages: np.ndarray
    displacements: np.ndarray

    @classmethod
    def from_polynomial(cls, axis: str, branch: str) -> "Branch":
        displacement = np.linspace(-10.0, STROKE_UM + 20.0, 2601)
        voltage = voltage_for(axis, branch, displacement)
        return cls(voltage, displacement)

    def __call__(self, voltage: float) -> float:
        # Linear beyond the table (np.interp would clamp).
        v, d = self.voltages, self.displacements
        if voltage < v[0]:
            return float(d[0] + (voltage - v[0]) * (d[1] - d[0]) / (v[1] - v[0]))
        if voltage > v[-1]:
            return float(d[-1] + (voltage - v[-1]) * (d[-1] - d[-2]) / (v[-1] - v[-2]))
        return float(np.interp(voltage, v, d))


#: The voltage range the lab measured the branches over (0 to 100 um on the rising one).
FIT_VOLTAGES = (-19.0, 96.0)
#: The two polynomials are separate fits and lie up to 17-18 % of stroke apart, more
#: than the "up to about 15 %" the sources report for the loop; the model's loop is
#: drawn this much towards their mean (a change of ~2 % of stroke).
BRANCH_GAP_SCALE = 0.75
#: Backlash of the widest play operator (volts) and how many operators.
MAX_BACKLASH_V = 25.0
OPERATORS = 26


class Hysteresis:
    """m(V) + g(V) * mean_r (play_r(V) - V) / mean(r), see the module docstring."""

    def __init__(self, axis: str):
        rising = Branch.from_polynomial(axis, "increasing")
        falling = Branch.from_polynomial(axis, "decreasing")
        voltages = np.linspace(nv40.VOLTAGE_MIN, nv40.VOLTAGE_MAX, 601)
        self._mean_voltages = voltages
        self._mean_displacements = np.array([(rising(v) + falling(v)) / 2 for v in voltages])
        self._half_gaps = BRANCH_GAP_SCALE * np.array([(falling(v) - rising(v)) / 2 for v in voltages])
        self.thresholds = np.linspace(0.0, MAX_BACKLASH_V, OPERATORS)
        self.voltage = FIT_VOLTAGES[0]
        self.state = self.voltage + self.thresholds  # relaxed, as after coming down
        self.displacement = self._output()

    def _output(self) -> float:
        mean = float(np.interp(self.voltage, self._mean_voltages, self._mean_displacements))
        half_gap = float(np.interp(self.voltage, self._mean_voltages, self._half_gaps))
        return mean + half_gap * float((self.state - self.voltage).sum()) / float(self.thresholds.sum())

    def apply(self, voltage: float) -> float:
        """Move to ``voltage``; returns the static displacement there."""
        voltage = min(max(voltage, nv40.VOLTAGE_MIN), nv40.VOLTAGE_MAX)
        self.state = np.clip(self.state, voltage - self.thresholds, voltage + self.thresholds)
        self.voltage = voltage
        self.displacement = self._output()
        return self.displacement


#: Creep is counted from this time after a step, for at most CREEP_DECADES decades.
CREEP_START_S = 0.1
CREEP_DECADES = 3.0


@dataclass
class PiezoAxis:
    """One stage axis: hysteresis, settling and creep, as a function of time.

    ``command(voltage, t)`` records a step at time ``t`` (seconds, simulated clock);
    ``position(t)`` is the displacement at any time after the first command. Creep of
    earlier steps is frozen into the axis's offset when a new step starts.
    """

    axis: str = "x"
    settle_s: float = 0.002
    creep_per_decade: float = 0.015
    hysteresis: Hysteresis = field(init=False)
    # Each step: (time, position just before, static target, creep offset so far).
    steps: list = field(default_factory=list)

    def __post_init__(self):
        self.hysteresis = Hysteresis(self.axis)
        start = self.hysteresis.displacement
        self.steps = [(-1e9, start, start, 0.0)]

    @property
    def voltage(self) -> float:
        return self.hysteresis.voltage

    def _creep(self, step: tuple, elapsed: float) -> float:
        _, before, target, offset = step
        decades = min(math.log10(1.0 + elapsed / CREEP_START_S), CREEP_DECADES)
        return (target - (before - offset)) * self.creep_per_decade * decades

    def command(self, voltage: float, t: float) -> None:
        index = self._step_at(t)
        previous = self.steps[index]
        offset = previous[3] + self._creep(previous, max(t - previous[0], 0.0))
        before = self.position(t)
        target = self.hysteresis.apply(voltage)
        self.steps.append((t, before, target, offset))
        if len(self.steps) > 64:  # older steps have long settled
            del self.steps[:-64]

    def _step_at(self, t: float) -> int:
        index = len(self.steps) - 1
        while index > 0 and self.steps[index][0] > t:
            index -= 1
        return index

    def position(self, t: float) -> float:
        """Displacement (um) at time ``t``, quantized to the stage's 0.2 nm resolution."""
        step = self.steps[self._step_at(t)]
        when, before, target, offset = step
        elapsed = max(t - when, 0.0)
        settled = offset + target - (offset + target - before) * math.exp(-elapsed / self.settle_s)
        return round((settled + self._creep(step, elapsed)) / RESOLUTION_UM) * RESOLUTION_UM

    def positions(self, times: np.ndarray) -> np.ndarray:
        return np.array([self.position(float(t)) for t in times])
