"""Displacement -> voltage models for an open-loop piezo stage (paper section II-E,
eq. 37 ff.: "these displacements are mapped to the respective channel voltages using our
displacement-voltage model").

The default is the lab's measured TRITOR model: fourth-order polynomials, one for the
increasing and one for the decreasing branch of the hysteresis; the model remembers the
direction each axis last moved in and uses that branch. Pluggable alternatives: a
linear model, and a model fitted by calibration and loaded from a JSON file.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from semservo.simulation.piezo import TRITOR_POLYNOMIALS


class DisplacementModel(Protocol):
    def voltage_for(self, target_um: float) -> float:
        """The voltage that should bring the axis to ``target_um`` (absolute travel)."""

    def reset(self, position_um: float) -> None:
        """Where the axis is now (its open-loop estimate), e.g. after homing."""

    def position_for(self, voltage: float) -> float:
        """The displacement the model expects at ``voltage`` (its inverse), e.g. to know
        where the axis is when the link opens."""

    def follow_voltage(self, voltage: float, previous_voltage: float) -> None:
        """The axis was driven to ``voltage`` directly (not through the model): take the
        direction of that move and the position the model expects there."""

    def max_slope_v_per_um(self) -> float:
        """The steepest the model gets (V per um)."""


#: The stroke (um) the branches are taken as monotonic over, and searched for the loop's ends.
STROKE_SEARCH_UM = (-10.0, 120.0)
#: A minor branch weighs the scaled branch by 1 - (1 - f)^n of the way f to the loop's far end
#: (:meth:`BranchModel._minor`): n = 1 still met the other branch, n = 4 bent too soon.
MINOR_LOOP_BLEND_POWER = 3


@dataclass
class BranchModel:
    """Hysteresis branches V = p(d) for increasing and decreasing displacement (the major
    loop, as calibrated), with a minor loop after a reversal that starts by Masing's rule
    and ends on the major branch scaled onto the rest of the loop.

    A reversal does not jump to the other branch: the branches are up to 15 % of the
    stroke apart, so a jump would turn a 0.1 um correction into a 10 V step, and a
    servo loop into a limit cycle. Nor does it take the other branch's slope where the
    axis is: a piezo that reverses starts a minor loop, steep at first (it moves little
    per volt just after it reverses). The minor branch from a reversal at (v_r, d_r)
    (``_minor``) blends two curves by the fraction f of the way from the reversal to the
    loop's far end e, where the two major branches meet:

    - near the reversal, Masing's rule: the major branch of the new direction from its
      start s, shifted to start at the reversal, ``v_r + p(s + d - d_r) - p(s)`` (the
      return of a Prandtl-Ishlinskii piezo while few of its play operators have
      switched, which depends on how far it has come back, not on how far it has to go);
    - towards the far end, scaling: the whole major branch mapped affinely onto the
      span from the reversal to (e, p(e)), heading for the last turning point not yet
      wiped out (Madelung's rule; with one reversal kept that is the loop's end).

    The minor branch is ``shifted + w(f) (scaled - shifted)`` with w(f) = 1 - (1 - f)^n,
    n = ``MINOR_LOOP_BLEND_POWER``: Masing's slope at the reversal (w(0) = 0), the far end
    reached (w(1) = 1), the scaled branch weighed in early (w = 0.5 a fifth of the way). On y, and
    on every rising return, it closes at the far end; on x after reversals high in the
    stroke it still meets the falling major branch first, later and more gently than
    the shifted branch (reversals at 60, 80, 90 um: 47, 33, 35 um into the return, its
    slope changing 1.5, 13, 6 % over 0.1 um there, against 19-23 um and 26-112 %). Each
    curve alone was worse in the closed loop. The shifted branch alone met the other
    major branch 19-24 um into the return (the lab's two fitted branches are not each
    other's mirror image), where its volts per micrometre fell by 37 % and the law's
    learned gain was ~30 % off. The scaled branch alone compresses the curvature near
    the reversal by the span's ratio (8 % fewer volts than Masing's 10 um back from a
    reversal at 60 um): a second move after a reversal did other than the first had (in
    one trial it left 12 % of its move, against 5 %), and starts 15 % of the field away
    took a fifth fresh frame (``semservo reproduce --only time_to_target``: a median of 5
    frames in six presets, 4 with the blend). A linear weight, w = f, still met the
    crossing on the x axis; one nearer the scaled branch, 1 - (1 - f)^4, took the fifth frame.

    Should the branch meet the major branch before the end (a reversal outside the
    loop), that branch is taken and the reversal forgotten. Only the last reversal is
    kept: the wiping-out of nested loops (back on the outer branch past the point an
    inner loop began) made the voltage jump there, because the lab's two fitted branches
    are not each other's mirror image; a held position's hundreds of small corrections
    found it (0.23 px off once in 10 simulated minutes).

    The major loop's ends are where the two branches come closest at either end of the
    stroke (``STROKE_SEARCH_UM``). ``offset_v`` is added to every voltage (0 unless a
    caller sets it).
    """

    increasing: tuple[float, ...]
    decreasing: tuple[float, ...]
    position_um: float = 0.0
    direction: int = 1
    offset_v: float = 0.0
    #: The last reversal: (voltage, displacement, direction of the branch that starts
    #: there), or None on a major branch; a tuple, replaced and never changed in place,
    #: so a shallow copy (a move tried out before it is made) cannot change the model.
    reversal: tuple | None = None
    #: The voltage the model last gave (without ``offset_v``); None: on the major branch.
    voltage: float | None = None

    def __post_init__(self):
        low, high = STROKE_SEARCH_UM
        stroke = np.linspace(low, high, 1301)
        gap = np.abs(np.polyval(self.increasing, stroke) - np.polyval(self.decreasing, stroke))
        third = len(stroke) // 3
        self.bottom_um = float(stroke[:third][np.argmin(gap[:third])])
        self.top_um = float(stroke[-third:][np.argmin(gap[-third:])])

    @classmethod
    def tritor(cls, axis: str) -> "BranchModel":
        """The lab's measured TRITOR model for axis "x" or "y"."""
        return cls(TRITOR_POLYNOMIALS[(axis, "increasing")], TRITOR_POLYNOMIALS[(axis, "decreasing")])

    def _branch(self) -> tuple[float, ...]:
        return self.increasing if self.direction > 0 else self.decreasing

    def _major(self, direction: int, displacement_um: float) -> float:
        return float(np.polyval(self.increasing if direction > 0 else self.decreasing, displacement_um))

    def _minor(self, direction: int, target_um: float) -> float | None:
        """The minor branch from the last reversal (v_r, d_r) at ``target_um`` (see the
        class docstring), with f = (d - d_r) / (e - d_r) the fraction of the way to the
        loop's far end e and s the major branch's start:
        shifted(d) = v_r + p(s + d - d_r) - p(s) (Masing),
        scaled(d) = v_r + (p(s + f (e - s)) - p(s)) (p(e) - v_r) / (p(e) - p(s)),
        V(d) = shifted(d) + (1 - (1 - f)^n) (scaled(d) - shifted(d)), n = ``MINOR_LOOP_BLEND_POWER``.
        None past the far end, or when the reversal lies beyond it (outside the loop)."""
        start_v, start_um, _ = self.reversal
        begin, end = (self.bottom_um, self.top_um) if direction > 0 else (self.top_um, self.bottom_um)
        span_um = end - start_um
        if span_um * direction <= 1e-9:
            return None
        fraction = (target_um - start_um) / span_um
        if fraction >= 1.0:
            return None
        major_begin, major_end = self._major(direction, begin), self._major(direction, end)
        shifted = start_v + self._major(direction, begin + target_um - start_um) - major_begin
        shaped = self._major(direction, begin + fraction * (end - begin)) - major_begin
        scaled = start_v + shaped * (major_end - start_v) / (major_end - major_begin)
        return shifted + (1.0 - (1.0 - fraction) ** MINOR_LOOP_BLEND_POWER) * (scaled - shifted)

    def voltage_for(self, target_um: float) -> float:
        if self.voltage is None:
            self.voltage = self._major(self.direction, self.position_um)
        if target_um != self.position_um:
            direction = 1 if target_um > self.position_um else -1
            if direction != self.direction:
                self.reversal = (self.voltage, self.position_um, direction)
                self.direction = direction
            major = self._major(direction, target_um)
            voltage = self._minor(direction, target_um) if self.reversal is not None else None
            if voltage is None or (voltage - major) * direction >= 0:
                # On the major branch, or met it: the loop closed, the reversal is forgotten.
                voltage = major
                self.reversal = None
            self.voltage = voltage
        self.position_um = target_um
        return self.voltage + self.offset_v

    def reset(self, position_um: float) -> None:
        """The axis stands at ``position_um`` on the major branch of its direction."""
        self.position_um = position_um
        self.offset_v = 0.0
        self.reversal = None
        self.voltage = None

    def position_for(self, voltage: float) -> float:
        """Inverse of the current branch by bisection over the stroke (-10..120 um; the
        branches are monotonic there)."""
        branch = self._branch()
        low, high = -10.0, 120.0
        for _ in range(60):
            middle = (low + high) / 2
            if np.polyval(branch, middle) + self.offset_v < voltage:
                low = middle
            else:
                high = middle
        return (low + high) / 2

    def follow_voltage(self, voltage: float, previous_voltage: float) -> None:
        """The axis now stands at ``voltage``: on its direction's major branch, the
        reversal forgotten (the position is the branch's inverse *without* the old offset, so
        that the next small move asks for a small change of voltage: inverting with the
        offset and then dropping it turned a 0.03 um correction after a reconnect into
        an 11 V jump)."""
        if voltage != previous_voltage:
            self.direction = 1 if voltage > previous_voltage else -1
        self.offset_v = 0.0
        self.reset(self.position_for(voltage))
        self.voltage = voltage

    def max_slope_v_per_um(self) -> float:
        """The steepest either branch gets over the stroke (V per um): bounds how much a
        move of a given size may change the voltage."""
        stroke = np.linspace(-10.0, 120.0, 261)
        return float(max(np.abs(np.polyval(np.polyder(branch), stroke)).max()
                         for branch in (self.increasing, self.decreasing)))

    def to_dict(self) -> dict:
        return {"kind": "branches", "increasing": list(self.increasing), "decreasing": list(self.decreasing)}


@dataclass
class LinearModel:
    """V = offset + d / gain (gain in um per volt)."""

    gain_um_per_v: float = 0.85
    offset_v: float = -19.0
    position_um: float = field(default=0.0)

    def voltage_for(self, target_um: float) -> float:
        self.position_um = target_um
        return self.offset_v + target_um / self.gain_um_per_v

    def reset(self, position_um: float) -> None:
        self.position_um = position_um

    def position_for(self, voltage: float) -> float:
        return (voltage - self.offset_v) * self.gain_um_per_v

    def follow_voltage(self, voltage: float, previous_voltage: float) -> None:
        self.reset(self.position_for(voltage))

    def max_slope_v_per_um(self) -> float:
        return 1.0 / abs(self.gain_um_per_v)

    def to_dict(self) -> dict:
        return {"kind": "linear", "gain_um_per_v": self.gain_um_per_v, "offset_v": self.offset_v}


def save_model(model: BranchModel | LinearModel, path: str | Path) -> Path:
    """Write a model (e.g. a calibration result) as JSON."""
    path = Path(path)
    path.write_text(json.dumps(model.to_dict(), indent=2))
    return path


def load_model(path: str | Path) -> BranchModel | LinearModel:
    """A model from a JSON file written by :func:`save_model` (or by hand)."""
    try:
        fields = json.loads(Path(path).read_text())
        if fields["kind"] == "branches":
            return BranchModel(tuple(map(float, fields["increasing"])), tuple(map(float, fields["decreasing"])))
        if fields["kind"] == "linear":
            return LinearModel(float(fields["gain_um_per_v"]), float(fields["offset_v"]))
        raise ValueError(f"unknown model kind {fields['kind']!r}")
    except (OSError, KeyError, TypeError, ValueError) as error:
        raise ValueError(f"{path}: not a displacement model ({error})") from None
