"""The stage service's core for a motion driver: axes that take micrometres and degrees
themselves (:class:`semservo.instruments.MotionDriver`: a closed-loop stage, a
microscope's own stage, its beam shift), beside the voltage-channel core
(:class:`services.stage.core.StageCore`, the NV 40/3) whose state, owner, watchdog,
stop, persistence and command log it shares.

The rules of a move, in order, as for the NV 40/3:

1. the stage must not be stopped or held, and the link must be up;
2. a run that has the stage armed moves it alone (``owned``);
3. each axis known, of the command's unit (``move``: micrometres, ``rotate``: degrees);
4. each goal within the axis's travel: the device's own, narrowed by the lab's
   (``SEMSERVO_STAGE__TRAVEL``); a NaN or an infinity is outside every travel;
5. each step at most ``max_step_um`` (``max_turn_deg`` for degrees), or the axis's own
   (``SEMSERVO_STAGE__MAX_STEPS``).

Refused whole, never clipped. What the device refuses comes back as ``device_refused`` in
its own words; a device that moved elsewhere than asked (a beam shift clipped by the
SDK, a stage that stopped short) is ``not_applied``. Positions are read back every
``READBACK_S``: an axis moved by anyone else (the microscope's own software, a joystick)
stops the stage with the reason, as a knob on the NV 40/3 does.
"""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass, field
from typing import Callable

from semservo.instruments import PHYSICAL, Axis, DeviceError, LinkError, MotionDriver, driver_kind

from services.stage.core import DEFAULT_SETTLE_S, Refused, StageCore, log

#: Read-back further than this from where the axis was left is a move nobody commanded
#: (per unit, and tighter for a beam shift, which does not jitter); settable per axis.
READBACK_TOLERANCE = {("um", "stage"): 0.2, ("um", "beam"): 0.01, ("deg", "stage"): 0.01, ("deg", "beam"): 0.01}
#: Where an axis must arrive, at most this far from its goal, or the move was not
#: applied as asked (a clipped beam shift, a stage that stopped short); settable per axis.
ARRIVAL_TOLERANCE = {("um", "stage"): 0.5, ("um", "beam"): 0.01, ("deg", "stage"): 0.05, ("deg", "beam"): 0.01}


@dataclass(frozen=True)
class PhysicalLimits:
    """The lab's limits for axes in physical units (beside :class:`StageLimits`)."""

    #: The largest displacement one command may ask of a micrometre axis.
    max_step_um: float = 10.0
    #: Per axis (its unit): a tighter or looser step than the default.
    max_steps: dict[str, float] = field(default_factory=dict)
    #: Per axis: the soft travel (absolute, in the device's coordinates), within its own.
    travel: dict[str, tuple[float, float]] = field(default_factory=dict)
    readback_tolerance: dict[str, float] = field(default_factory=dict)
    arrival_tolerance: dict[str, float] = field(default_factory=dict)


@dataclass
class PhysicalStageCore(StageCore):
    """:class:`StageCore` on a :class:`~semservo.instruments.MotionDriver`: the same
    commands and rules, in micrometres and degrees instead of volts."""

    channels: dict[str, int] = field(default_factory=dict)  # no voltage channels
    open_driver: Callable[[str], MotionDriver] | None = None
    physical: PhysicalLimits = field(default_factory=PhysicalLimits)

    def __post_init__(self):
        if self.open_driver is None:
            raise ValueError("a physical stage core needs its motion driver (open_driver)")
        super().__post_init__()
        self.axes: dict[str, Axis] = {}
        self.where: dict[str, float] = {}  # every axis as last read back (after our own moves too)

    # -- the link ----------------------------------------------------------------------
    def connect(self) -> bool:
        """Open the driver, identify the device, read its axes and where they are.
        False (and the reason in health) if any of it fails."""
        if self.rotation_link == "not used yet":
            self._read_rotation_stage()
        self.close()
        try:
            self.driver = self.open_driver(self.url)
            if driver_kind(self.driver) != PHYSICAL:
                raise DeviceError(f"{type(self.driver).__name__} is not a motion driver (kind {PHYSICAL!r}); an "
                                  f"amplifier's driver runs on the voltage core")
            self.driver.on_entry = self._journal_entry
            self.device = self.driver.identify()
            self.axes = self._checked_axes(self.driver.axes())
            measured = self.driver.read_positions()
            missing = [axis for axis in self.axes if axis not in measured]
            if missing:
                raise DeviceError(f"the device does not say where {', '.join(missing)} is")
        except (LinkError, DeviceError) as error:
            self._lost(f"cannot connect to {self.url}: {error}")
            return False
        before = dict(self.where)
        self.where = {axis: float(measured[axis]) for axis in self.axes}
        changed = {axis: (before[axis], self.where[axis]) for axis in before
                   if axis in self.where and abs(self.where[axis] - before[axis]) > self._tolerance(axis, "readback")}
        if self.link != "connected" and self.counters["link_lost"]:
            self.counters["reconnects"] += 1
        self.link, self.attempts, self.last_error = "connected", 0, None
        self.last_io = self.clock()
        log.info("motion driver on %s: %s, axes %s", self.url, self.device.get("model"),
                 ", ".join(f"{axis} ({info.moves}, {info.unit})" for axis, info in self.axes.items()))
        self._uncommanded(changed, "while the link was down", "moved by hand or by the microscope's own software")
        return True

    def _checked_axes(self, axes: dict[str, Axis]) -> dict[str, Axis]:
        """The device's axes, each with a finite travel (its own, or the lab's): an axis
        without one could be sent anywhere, and is refused at connect."""
        checked = {}
        for name, axis in axes.items():
            if axis.unit not in ("um", "deg") or axis.moves not in ("stage", "beam"):
                raise DeviceError(f"axis {name!r}: unit must be um or deg and moves stage or beam, got "
                                  f"{axis.unit!r}, {axis.moves!r}")
            low, high = axis.travel
            soft = self.physical.travel.get(name)
            if soft is not None:
                low, high = max(low, soft[0]), min(high, soft[1])
            if not (math.isfinite(low) and math.isfinite(high) and low <= high):
                raise DeviceError(f"axis {name!r} has no finite travel (device {axis.travel}, lab {soft}): set "
                                  f"SEMSERVO_STAGE__TRAVEL='{{\"{name}\": [min, max]}}'")
            checked[name] = Axis(axis.unit, axis.moves, (float(low), float(high)))
        return checked

    def _tolerance(self, axis: str, which: str) -> float:
        own = (self.physical.readback_tolerance if which == "readback" else self.physical.arrival_tolerance).get(axis)
        if own is not None:
            return own
        info = self.axes[axis]
        return (READBACK_TOLERANCE if which == "readback" else ARRIVAL_TOLERANCE)[(info.unit, info.moves)]

    def poll(self) -> float:
        """As :meth:`StageCore.poll`; a watchdog hold also halts the driver (a motorized
        stage may still be on its way; an amplifier has nothing to halt)."""
        before = self.state
        wait = super().poll()
        if before == "ready" and self.state == "held" and self.driver is not None and self.link == "connected":
            try:
                self.driver.halt()
            except (LinkError, DeviceError) as error:
                self.last_error = f"held, but the driver's halt failed: {error}"
                log.error("%s", self.last_error)
        return wait

    def _read_back(self, driver):
        return driver.read_positions()

    def _compare(self, measured) -> None:
        """Axes where nobody here moved them: stop, say what changed, follow them."""
        changed = {axis: (self.where[axis], float(measured[axis])) for axis in self.where if axis in measured
                   and abs(float(measured[axis]) - self.where[axis]) > self._tolerance(axis, "readback")}
        for axis, (_before, after) in changed.items():
            self.where[axis] = after
        self._uncommanded(changed, "without a command from semservo",
                          "the microscope's own software, a joystick or another client")

    def _uncommanded(self, changed: dict[str, tuple[float, float]], when: str, suspects: str) -> None:
        if not changed:
            return
        self.counters["uncommanded_changes"] += 1
        what = ", ".join(f"{axis} {before:.4f} -> {after:.4f} {self.axes[axis].unit}"
                         for axis, (before, after) in changed.items())
        self.stop(f"the axes moved {when} ({what}): {suspects}? Check the stage, then resume")

    def _voltages_text(self) -> str:
        return ", ".join(f"{axis} {value:.4f} {self.axes[axis].unit}" for axis, value in self.where.items())

    def rebase(self) -> dict[str, float]:
        """Take where the axes are now as where they were left, without calling it a move
        nobody commanded: for a lab script that moves its microscope itself between runs
        (:class:`semservo.openfibsem.Positioner`). Refused while a run has the stage armed."""
        if self.watchdog.armed:
            raise Refused("owned", f"a run ({self.watchdog.owner}) has the stage armed")
        self.where.update(self._io(self._read_back))
        return dict(self.where)

    # -- commands ----------------------------------------------------------------------
    def positions(self) -> dict[str, float]:
        return {axis: value for axis, value in self.where.items() if self.axes[axis].unit == "um"}

    def angles(self) -> dict[str, float]:
        return {axis: value for axis, value in self.where.items() if self.axes[axis].unit == "deg"}

    def max_step(self, axis: str) -> float:
        own = self.physical.max_steps.get(axis)
        if own is not None:
            return own
        return self.physical.max_step_um if self.axes[axis].unit == "um" else self.limits.max_turn_deg

    def _move_axes(self, targets: dict[str, float], relative: bool, owner: str | None, unit: str) -> dict:
        """The rules of a move (see the module), then one command to the driver."""
        try:
            self._check_ready()
            self._check_owner(owner)
            axes = {axis: info for axis, info in self.axes.items() if info.unit == unit}
            unknown = [axis for axis in targets if axis not in axes]
            if unknown:
                raise Refused("bad_axis", f"unknown axis {unknown[0]!r}; axes in {unit}: {', '.join(axes) or 'none'}")
            goal, steps = {}, {}
            for axis, value in targets.items():
                goal[axis] = self.where[axis] + value if relative else value
                low, high = axes[axis].travel
                if not low <= goal[axis] <= high:  # NaN and infinities fail this too
                    raise Refused("travel_limit" if unit == "um" else "rotation_limit",
                                  f"{axis}: {goal[axis]:.4g} {unit} is outside the travel {low:g}..{high:g} {unit}")
                steps[axis] = goal[axis] - self.where[axis]
                if abs(steps[axis]) > self.max_step(axis):
                    raise Refused("step_limit", f"{axis}: a {abs(steps[axis]):.4g} {unit} step exceeds the maximum "
                                                f"of {self.max_step(axis):g} {unit} per command")
        except Refused:
            self.counters["refused"] += 1
            raise
        written_at_ns = time.time_ns()
        try:
            measured = self._io(lambda driver: driver.move_by(steps))
        except DeviceError as error:
            self.counters["refused"] += 1
            self._refresh()  # a refused command may still have moved something: know where
            raise Refused("device_refused", f"the device refused the move: {error}") from None
        self.where.update({axis: float(measured[axis]) for axis in self.axes if axis in measured})
        if owner is not None and owner == self.watchdog.owner:
            self.watchdog.last_contact = self.clock()
        self.counters["moves" if unit == "um" else "turns"] += 1
        missed = {axis: self.where[axis] for axis in goal
                  if abs(self.where[axis] - goal[axis]) > self._tolerance(axis, "arrival")}
        if missed:
            raise Refused("not_applied", "the device did not go where it was sent: "
                          + ", ".join(f"{axis} at {self.where[axis]:.4f} {unit}, sent to {goal[axis]:.4f}"
                                      for axis in missed) + " (clipped to its own limits, or stopped short)")
        settles = getattr(self.driver, "settles_in_s", None)
        settle_s = max([self.settle_s.get(axis, DEFAULT_SETTLE_S) for axis in goal]
                       + [float(settles()) if callable(settles) else 0.0])
        return {"written_at_ns": written_at_ns, "goal": goal, "settled_at_ns": written_at_ns + int(settle_s * 1e9)}

    def _refresh(self) -> None:
        with contextlib.suppress(Refused):  # unreadable now: the positions last read stand
            self.where.update(self._io(self._read_back))

    def move(self, targets: dict[str, float], *, relative: bool = False, owner: str | None = None) -> dict:
        """Move micrometre axes to ``targets`` (the device's coordinates) or by them
        (``relative``); the rules of the module apply."""
        moved = self._move_axes(targets, relative, owner, "um")
        return {"written_at_ns": moved["written_at_ns"], "voltages": {}, "positions_um": self.positions(),
                "settled_at_ns": moved["settled_at_ns"]}

    def rotate(self, targets: dict[str, float], *, relative: bool = False, owner: str | None = None) -> dict:
        """Turn or tilt: a separate rotation-and-tilt stage if the lab has one, else the
        motion driver's degree axes (a microscope stage's rotation and tilt)."""
        if self.rotation is not None:
            return super().rotate(targets, relative=relative, owner=owner)
        moved = self._move_axes(targets, relative, owner, "deg")
        return {"written_at_ns": moved["written_at_ns"], "angles_deg": self.angles(),
                "targets_deg": {**self.angles(), **moved["goal"]}, "settled_at_ns": moved["settled_at_ns"]}

    def set_voltages(self, volts: dict[str, float], *, owner: str | None = None) -> dict:
        self.counters["refused"] += 1
        raise Refused("no_voltages", f"this stage's driver ({self.device.get('model') or self.url}) takes "
                                     f"micrometres and degrees, not voltages: use move")

    def release(self) -> dict:
        """Nothing to hand back to a front panel: the stage stops (and says so)."""
        return self.stop("released")

    def describe(self) -> dict:
        described = super().describe()
        described["positions_um"] = self.positions()
        described["settle_s"] = {axis: self.settle_s.get(axis, DEFAULT_SETTLE_S) for axis in self.axes}
        described["kind"] = PHYSICAL
        described["axes"] = {axis: {"unit": info.unit, "moves": info.moves, "position": self.where.get(axis),
                                    "travel": list(info.travel), "max_step": self.max_step(axis)}
                             for axis, info in self.axes.items()}
        if self.rotation is None and self.angles():
            # The controller finds turning axes here, as for a rotation-and-tilt stage.
            described["rotation"] = {"angles_deg": self.angles(), "link": self.link,
                                     "travel_deg": {axis: list(info.travel) for axis, info in self.axes.items()
                                                    if info.unit == "deg"}}
        return described


def physical_core(url: str, driver: type, config, limits, rotation=None) -> PhysicalStageCore:
    """The stage service's core for a motion driver class, from the stage settings
    (:class:`semservo.config.StageSettings`)."""
    return PhysicalStageCore(url, limits=limits, open_driver=driver.open, state_dir=config.state_dir,
                             rotation=rotation, settle_s=dict(config.settle_s),
                             physical=PhysicalLimits(config.max_step_um, dict(config.max_steps),
                                                     {axis: tuple(span) for axis, span in config.travel.items()},
                                                     dict(config.readback_tolerance), dict(config.arrival_tolerance)))
