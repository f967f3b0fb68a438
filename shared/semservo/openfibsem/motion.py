"""A motion driver for a microscope through OpenFIBSEM: its stage (``stable_move`` or
``move_stage_relative``) and its beam shift, as semservo axes in micrometres.

Axes (:class:`semservo.instruments.Axis`):

* ``x``, ``y``: the stage, in the image plane (x right, y down as displayed), in
  micrometres from where the stage was when the driver connected. fibsem's
  ``stable_move`` moves the view by (dx, dy) and corrects y for the pre-tilt and tilt
  (the stage's y and z move together); ``stage_move=relative`` moves raw x and y.
* ``beam_x``, ``beam_y``: the beam shift, absolute, in micrometres, moving the content
  as ``x``, ``y`` do; its travel is the SDK's limits where fibsem exposes them (Thermo
  Fisher's AutoScript), else ``beam_limit_um`` (default +-10 um).

Units and signs: :mod:`semservo.openfibsem.units`, and nowhere else. What the microscope
refuses is a :class:`~semservo.instruments.DeviceError` in its words: a stage move whose
end lies outside the stage's range (fibsem's ``_get_axis_limits``, checked before the
move, as the SDK would refuse it), a beam shift beyond its limit (refused here: the
SDK would clip it in silence), and any exception fibsem raises.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any, Callable, ClassVar

from semservo.instruments import PHYSICAL, Axis, DeviceError, LinkError, LogEntry
from semservo.openfibsem import session, units


class OpenFibsemMotion:
    """:class:`~semservo.instruments.MotionDriver` over an OpenFIBSEM microscope
    (``FibsemMicroscope``: Thermo Fisher, TESCAN, the DemoMicroscope)."""

    kind = PHYSICAL
    #: Per URL, where the stage was when first connected (the origin of ``x`` and ``y``),
    #: so a reconnect reads the same positions, as a closed-loop stage's do.
    origins: ClassVar[dict[str, tuple[float, float, float]]] = {}

    def __init__(self, microscope: Any, *, beam: str = "electron", stage_move: str = "stable",
                 beam_limit_um: float | None = None, stage_signs: tuple[int, int] = units.STAGE_SIGNS,
                 beam_signs: tuple[int, int] = units.BEAM_SIGNS, origin: tuple[float, float, float] | None = None,
                 owns_microscope: bool = False):
        session.require_fibsem()
        if stage_move not in ("stable", "relative"):
            raise ValueError(f"stage_move must be stable or relative, got {stage_move!r}")
        self.microscope = microscope
        self.beam = session.beam_type(beam)
        self.stage_move = stage_move
        self.beam_limit_um = beam_limit_um
        self.stage_signs, self.beam_signs = tuple(stage_signs), tuple(beam_signs)
        self.owns_microscope = owns_microscope
        self.log: list[LogEntry] = []
        self.on_entry: Callable[[LogEntry], None] | None = None
        self.lock = threading.Lock()
        position = self._call("get_stage_position()", microscope.get_stage_position)
        self.origin = origin or (float(position.x), float(position.y), float(position.z))

    @classmethod
    def open(cls, url: str) -> "OpenFibsemMotion":
        """``openfibsem://MANUFACTURER@HOST?options`` (:mod:`semservo.openfibsem.session`)."""
        try:
            address = session.Address.parse(url)
        except ValueError as error:
            raise DeviceError(str(error)) from None
        options = address.options
        try:
            microscope = session.connect(address.manufacturer, address.host, options.get("config"))
        except ImportError:
            raise
        except Exception as error:  # noqa: BLE001 - an SDK fails to connect in its own ways; say which
            raise LinkError(f"cannot connect to the {address.manufacturer} microscope at {address.host}: "
                            f"{type(error).__name__}: {error}") from None
        try:
            driver = cls(microscope, beam=options.get("beam", "electron"),
                         stage_move=options.get("stage_move", "stable"),
                         beam_limit_um=float(options["beam_limit_um"]) if "beam_limit_um" in options else None,
                         stage_signs=units.signs_from_text(options.get("stage_signs"), units.STAGE_SIGNS),
                         beam_signs=units.signs_from_text(options.get("beam_signs"), units.BEAM_SIGNS),
                         origin=cls.origins.get(url))
        except ValueError as error:
            raise DeviceError(f"{url}: {error}") from None
        cls.origins.setdefault(url, driver.origin)
        return driver

    # -- talking to the microscope -------------------------------------------------------
    def _entry(self, direction: str, text: str) -> None:
        entry = LogEntry(time.time_ns(), direction, text)
        self.log.append(entry)
        if self.on_entry is not None:
            self.on_entry(entry)

    def _call(self, text: str, action: Callable[[], Any], *, logged: bool = False):
        """One call into fibsem; what it raises becomes the device's refusal in its own
        words (a lost connection: :class:`LinkError`)."""
        if logged:
            self._entry("sent", text)
        try:
            result = action()
        except (ConnectionError, TimeoutError) as error:
            raise LinkError(f"{text}: {type(error).__name__}: {error}") from None
        except Exception as error:  # noqa: BLE001 - the SDK's own refusal, passed on in its words
            raise DeviceError(f"{text}: {type(error).__name__}: {error}") from None
        if logged:
            self._entry("received", repr(result))
        return result

    def identify(self) -> dict:
        info = self.microscope.system.info
        model = " ".join(str(part) for part in (info.manufacturer, info.model) if part)
        return {"model": model or type(self.microscope).__name__, "serial_number": info.serial_number,
                "software_version": info.software_version, "beam": self.beam.name.lower()}

    def _stage_limits(self) -> dict:
        return self._call("_get_axis_limits()", self.microscope._get_axis_limits)

    def beam_limits_um(self) -> tuple[tuple[float, float], tuple[float, float], str]:
        """The beam shift's travel (x, y, in semservo's um) and where it comes from: the
        SDK's limits (AutoScript's ``beam_shift.limits``) or ``beam_limit_um``."""
        try:
            limits = self.microscope._get_beam(beam_type=self.beam).beam_shift.limits
            low = units.to_micrometres(limits.limits_x.min, limits.limits_y.min, self.beam_signs)
            high = units.to_micrometres(limits.limits_x.max, limits.limits_y.max, self.beam_signs)
            return ((min(low[0], high[0]), max(low[0], high[0])), (min(low[1], high[1]), max(low[1], high[1])),
                    "the microscope's beam shift limits")
        except Exception:  # noqa: BLE001 - fibsem exposes them for AutoScript only
            limit = self.beam_limit_um if self.beam_limit_um is not None else session.DEFAULT_BEAM_LIMIT_UM
            return (-limit, limit), (-limit, limit), f"beam_limit_um {limit:g} (this SDK reports no limits)"

    def axes(self) -> dict[str, Axis]:
        limits = self._stage_limits()
        x0, y0, _ = self.origin
        x_span = sorted(self.stage_signs[0] * (value - x0) / units.METRES_PER_UM
                        for value in (limits["x"].min, limits["x"].max))
        # The image-plane y of the stage's y travel (z moves with it in a stable move: the
        # driver checks the stage's own x, y and z limits before every move).
        y_span = sorted(self.stage_signs[1] * (value - y0) / units.METRES_PER_UM
                        for value in (limits["y"].min, limits["y"].max))
        beam_x, beam_y, _ = self.beam_limits_um()
        return {"x": Axis("um", "stage", tuple(x_span)), "y": Axis("um", "stage", tuple(y_span)),
                "beam_x": Axis("um", "beam", beam_x), "beam_y": Axis("um", "beam", beam_y)}

    def read_positions(self) -> dict[str, float]:
        with self.lock:
            position = self._call("get_stage_position()", self.microscope.get_stage_position)
            shift = self._call("get_beam_shift()", lambda: self.microscope.get_beam_shift(self.beam))
            x0, y0, z0 = self.origin
            if self.stage_move == "stable":
                # Back from the stage's y and z to the view's y (fibsem's own inverse).
                image_y = self._call("_inverse_y_corrected_stage_movement()", lambda: float(
                    self.microscope._inverse_y_corrected_stage_movement(dy=float(position.y) - y0,
                                                                        dz=float(position.z) - z0,
                                                                        beam_type=self.beam)))
            else:
                image_y = float(position.y) - y0
            x_um, y_um = units.to_micrometres(float(position.x) - x0, image_y, self.stage_signs)
            beam_x, beam_y = units.to_micrometres(float(shift.x), float(shift.y), self.beam_signs)
            return {"x": x_um, "y": y_um, "beam_x": beam_x, "beam_y": beam_y}

    def move_by(self, steps: dict[str, float]) -> dict[str, float]:
        """The stage first (x, y), then the beam shift (beam_x, beam_y)."""
        unknown = set(steps) - {"x", "y", "beam_x", "beam_y"}
        if unknown:
            raise DeviceError(f"no axis {', '.join(sorted(unknown))} on an OpenFIBSEM microscope")
        stage = (steps.get("x", 0.0), steps.get("y", 0.0))
        beam = (steps.get("beam_x", 0.0), steps.get("beam_y", 0.0))
        with self.lock:
            if any(stage):
                self._move_stage(*stage)
            if any(beam):
                self._shift_beam(*beam)
        return self.read_positions()

    def _move_stage(self, x_um: float, y_um: float) -> None:
        from fibsem.structures import FibsemStagePosition

        dx, dy = units.stage_move_m(x_um, y_um, self.stage_signs)
        current = self._call("get_stage_position()", self.microscope.get_stage_position)
        if self.stage_move == "stable":
            goal = self._call("project_stable_move()", lambda: self.microscope.project_stable_move(
                dx=dx, dy=dy, beam_type=self.beam, base_position=current))
        else:
            goal = FibsemStagePosition(x=current.x + dx, y=current.y + dy, z=current.z, r=current.r, t=current.t)
        limits = self._stage_limits()
        for axis in ("x", "y", "z"):
            value, limit = getattr(goal, axis), limits.get(axis)
            if limit is not None and value is not None and not limit.min <= float(value) <= limit.max:
                raise DeviceError(f"the stage's {axis} would go to {float(value):.6g} m, outside its range {limit}")
        if self.stage_move == "stable":
            self._call(f"stable_move(dx={dx:.9g}, dy={dy:.9g}, beam_type={self.beam.name})",
                       lambda: self.microscope.stable_move(dx=dx, dy=dy, beam_type=self.beam), logged=True)
        else:
            move = FibsemStagePosition(x=dx, y=dy, z=0.0, r=0.0, t=0.0, coordinate_system="RAW")
            self._call(f"move_stage_relative(x={dx:.9g}, y={dy:.9g})",
                       lambda: self.microscope.move_stage_relative(move), logged=True)

    def _shift_beam(self, x_um: float, y_um: float) -> None:
        shift = self._call("get_beam_shift()", lambda: self.microscope.get_beam_shift(self.beam))
        here = units.to_micrometres(float(shift.x), float(shift.y), self.beam_signs)
        goal = (here[0] + x_um, here[1] + y_um)
        x_span, y_span, source = self.beam_limits_um()
        for name, value, (low, high) in (("x", goal[0], x_span), ("y", goal[1], y_span)):
            if not (math.isfinite(value) and low <= value <= high):
                raise DeviceError(f"a beam shift of {value:.4g} um in {name} is beyond its limit "
                                  f"{low:g}..{high:g} um ({source})")
        dx, dy = units.beam_shift_m(x_um, y_um, self.beam_signs)
        self._call(f"beam_shift(dx={dx:.9g}, dy={dy:.9g}, beam_type={self.beam.name})",
                   lambda: self.microscope.beam_shift(dx=dx, dy=dy, beam_type=self.beam), logged=True)

    def settles_in_s(self) -> float:
        """fibsem's moves return once the stage has arrived."""
        return 0.0

    def halt(self) -> None:
        """fibsem's moves block until they end, so none is in progress when the stage
        service can halt: nothing to stop."""

    def close(self) -> None:
        """The microscope stays connected (the image source of this process may share
        it); the process's end closes it."""
