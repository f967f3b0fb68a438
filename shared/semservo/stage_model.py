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


@dataclass
class BranchModel:
    """Hysteresis branches V = p(d) for increasing and decreasing displacement, with the
    direction of the last move remembered (a move in the same direction stays on its
    branch; a reversal switches).

    A reversal does not jump to the other branch: the branches are up to 15 % of the
    stroke apart, so a jump would turn a 0.1 um correction into a 10 V step, and a
    servo loop into a limit cycle. The new branch is followed with an offset that makes
    the voltage continuous at the reversal point (a minor loop starts where the axis
    is), and the offset fades over ``merge_um`` of travel as the minor loop joins the
    major branch.
    """

    increasing: tuple[float, ...]
    decreasing: tuple[float, ...]
    position_um: float = 0.0
    direction: int = 1
    offset_v: float = 0.0
    merge_um: float = 25.0

    @classmethod
    def tritor(cls, axis: str) -> "BranchModel":
        """The lab's measured TRITOR model for axis "x" or "y"."""
        return cls(TRITOR_POLYNOMIALS[(axis, "increasing")], TRITOR_POLYNOMIALS[(axis, "decreasing")])

    def _branch(self) -> tuple[float, ...]:
        return self.increasing if self.direction > 0 else self.decreasing

    def voltage_for(self, target_um: float) -> float:
        if target_um != self.position_um:
            direction = 1 if target_um > self.position_um else -1
            if direction != self.direction:
                here = float(np.polyval(self._branch(), self.position_um)) + self.offset_v
                self.direction = direction
                self.offset_v = here - float(np.polyval(self._branch(), self.position_um))
            self.offset_v *= float(np.exp(-abs(target_um - self.position_um) / self.merge_um))
        self.position_um = target_um
        return float(np.polyval(self._branch(), target_um)) + self.offset_v

    def reset(self, position_um: float) -> None:
        self.position_um = position_um
        self.offset_v = 0.0

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
        """The axis now stands at ``voltage``: on its direction's branch, the minor loop's
        offset gone (the position is the branch's inverse *without* the old offset, so
        that the next small move asks for a small change of voltage: inverting with the
        offset and then dropping it turned a 0.03 um correction after a reconnect into
        an 11 V jump)."""
        if voltage != previous_voltage:
            self.direction = 1 if voltage > previous_voltage else -1
        self.offset_v = 0.0
        self.reset(self.position_for(voltage))

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
