"""The simulated rotation-and-tilt stage (a goniometer): rotation about the beam and two
tilts, each axis moving at a finite speed towards its target, with a little backlash.

Geometry (what :mod:`semservo.simulation.sem` renders): the sample sits on the rotation
stage (it turns about the sample's own normal), which sits on the tilt cradle, whose
two axes are fixed in the chamber along the image's x and y and cross at a pivot
``pivot_depth_um`` below the sample surface: a tilt not only turns the surface but also
shifts the view, as on a real stage whose tilt axis is not at the sample's height.

Backlash: each axis is geared; when it reverses, the motor turns through the gear's
play (``backlash_deg``) before the output moves. The output follows the motor inside a
dead band of that width: it is what the sample does; the motor is what was commanded.
Times are the world's simulated seconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

#: Each axis's travel (degrees).
LIMITS_DEG = {"rotation_deg": (-360.0, 360.0), "tilt_x_deg": (-45.0, 45.0), "tilt_y_deg": (-45.0, 45.0)}
#: Speeds (degrees per simulated second): a motorised goniometer's, of the order of a
#: few degrees a second for tilt and ten for rotation.
SPEED_DEG_PER_S = {"rotation_deg": 10.0, "tilt_x_deg": 4.0, "tilt_y_deg": 4.0}
#: Gear play (degrees): the output lags the motor by half of it after a reversal.
BACKLASH_DEG = {"rotation_deg": 0.01, "tilt_x_deg": 0.01, "tilt_y_deg": 0.01}
#: Depth of the tilt axes below the sample surface (um): a tilt by t shifts the view by
#: about pivot x sin t.
PIVOT_DEPTH_UM = 20.0


@dataclass
class _Axis:
    """One geared axis: the motor ramps at ``speed`` from ``start`` (at ``since``) to
    ``target``; the output trails the motor within the gear's play."""

    speed: float
    backlash: float
    start: float = 0.0
    target: float = 0.0
    since: float = 0.0
    output_at_since: float = 0.0

    def motor(self, t: float) -> float:
        travelled = max(t - self.since, 0.0) * self.speed
        distance = self.target - self.start
        if abs(distance) <= travelled:
            return self.target
        return self.start + travelled * (1 if distance > 0 else -1)

    def output(self, t: float) -> float:
        motor, half = self.motor(t), self.backlash / 2
        # The output moves only once the motor pushes it from one side of the play.
        return min(max(self.output_at_since, motor - half), motor + half)

    def command(self, target: float, t: float) -> None:
        self.output_at_since = self.output(t)
        self.start, self.target, self.since = self.motor(t), target, t

    def arrival(self) -> float:
        """Simulated time at which the motor reaches its target."""
        return self.since + abs(self.target - self.start) / self.speed


@dataclass
class Goniometer:
    """The rotation-and-tilt stage. ``command`` sets targets (checked, refused whole);
    ``angles(t)`` is where the sample is at simulated time ``t``."""

    limits: dict = field(default_factory=lambda: dict(LIMITS_DEG))
    speeds: dict = field(default_factory=lambda: dict(SPEED_DEG_PER_S))
    backlash: dict = field(default_factory=lambda: dict(BACKLASH_DEG))
    pivot_depth_um: float = PIVOT_DEPTH_UM

    def __post_init__(self):
        self.axes = {name: _Axis(self.speeds[name], self.backlash[name]) for name in self.limits}

    def check(self, angles: dict) -> dict[str, float]:
        """The targets as floats, or ValueError naming the first bad one."""
        checked = {}
        for key, value in angles.items():
            if key not in self.limits:
                raise ValueError(f"unknown rotation stage axis {key!r}; axes: {', '.join(self.limits)}")
            low, high = self.limits[key]
            value = float(value)
            if not low <= value <= high:  # NaN fails this too
                raise ValueError(f"{key} must be a number of degrees within {low:g}..{high:g}, got {value!r}")
            checked[key] = value
        return checked

    def command(self, t: float, **angles: float) -> dict[str, float]:
        """Move towards these targets from simulated time ``t``; returns all targets."""
        for key, value in self.check(angles).items():
            self.axes[key].command(value, t)
        return self.targets()

    def halt(self, t: float) -> None:
        """Stop every axis where its motor is at ``t``."""
        for axis in self.axes.values():
            axis.command(axis.motor(t), t)

    def angles(self, t: float) -> dict[str, float]:
        return {name: axis.output(t) for name, axis in self.axes.items()}

    def targets(self) -> dict[str, float]:
        return {name: axis.target for name, axis in self.axes.items()}

    def arrival(self) -> float:
        """Simulated time at which every axis has reached its target."""
        return max(axis.arrival() for axis in self.axes.values())
