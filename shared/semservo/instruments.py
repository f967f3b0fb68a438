"""The two interfaces a lab writes against to plug in its own instruments, and how
semservo finds what it wrote.

* An **image source** delivers frames with what it knows of their acquisition
  (:class:`ImageSource`; subclass :class:`ImageSourceAdapter`). semservo ships ``sim``
  (the fake lab's SEM), ``replay`` (a folder, again and again) and ``watch`` (the
  folder an SEM's own software saves into). A vendor's API goes into an adapter.
* A **stage driver** sets and reads back the outputs of an amplifier or controller
  (:class:`StageDriver`). The NV 40/3 on RS-232
  (:class:`semservo.nv40_driver.NV403Driver`) is one; the stage service applies its
  safety rules (limits, step, rate, watchdog, stop, read-back) to every driver.
* A **motion driver** moves axes in physical units, micrometres or degrees, and reports
  where they are (:class:`MotionDriver`): a closed-loop stage, a microscope's own stage,
  its beam shift (:class:`semservo.openfibsem.OpenFibsemMotion` is one for Thermo Fisher
  and TESCAN microscopes through OpenFIBSEM). The stage service applies the same rules
  (travel and step per axis, the run's owner, stop, watchdog, read-back, command log).
  Which of the two a driver is: :func:`driver_kind`.

Each is named in the settings by an entry point (groups :data:`IMAGE_SOURCE_GROUP`,
:data:`STAGE_DRIVER_GROUP`) or a dotted path ``package.module:ClassName``.
``docs/instruments.md`` walks through both with a worked example.
"""

from __future__ import annotations

import abc
import importlib
import importlib.metadata
import math
from dataclasses import dataclass
from typing import Any, Callable, Protocol, runtime_checkable

import numpy as np

from semservo.messages import ACQUISITION_FIELDS
from semservo.sem_metadata import ImageMetadata

IMAGE_SOURCE_GROUP = "semservo.image_sources"
STAGE_DRIVER_GROUP = "semservo.stage_drivers"


# -- image sources -------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class AcquiredImage(ImageMetadata):
    """One image as a source delivers it, with its acquisition (the fields of
    :class:`~semservo.sem_metadata.ImageMetadata`: pixel size, magnification, dwell,
    working distance, ...). Fields a source does not know stay None: the frame header
    says "not known", never a made-up value."""

    pixels: np.ndarray  # 2-D, uint8, uint16 or float32; sample only (no data bar)
    acquired_at_ns: int  # Unix time the image was complete
    label: str | None = None
    scan_started_at_ns: int | None = None  # None: the source does not know (a file)
    source_interval_s: tuple[float, float] | None = None

    def acquisition(self) -> dict[str, Any]:
        """The acquisition fields that are known (what goes into the frame header)."""
        return {key: getattr(self, key) for key in ACQUISITION_FIELDS if getattr(self, key) is not None}


def scan_middle_ns(scan_started_at_ns: int | None, acquired_at_ns: int) -> int:
    """When a frame's content was seen, on average: the middle of its scan, or its
    acquisition time where the scan's start is unknown (then every frame of the source
    is late by the same scan time, and differences between frames still hold)."""
    if scan_started_at_ns is None or scan_started_at_ns > acquired_at_ns:
        return int(acquired_at_ns)
    return (int(scan_started_at_ns) + int(acquired_at_ns)) // 2


def capabilities(source: Any) -> set[str]:
    """What an image source can do beyond acquiring frames (``scan_settings``,
    ``focus``, ``scan_once``): from its ``capabilities()``, none when it has none."""
    method = getattr(source, "capabilities", None)
    return set(method()) if callable(method) else set()


class SourceUnavailable(RuntimeError):
    """The source cannot deliver a frame now (the microscope does not answer, the
    scan failed). The image server says so in health and asks again a second later."""


class NotSupported(RuntimeError):
    """The instrument cannot do what was asked (a capability it lacks, such as focus on
    a replayed folder); the image server answers it as a refusal in these words."""


class NotReady(Exception):
    """No new frame yet (the scan is still running); not an error, not the end."""


@runtime_checkable
class ImageSource(Protocol):
    """What the image server asks of a frame source.

    ``acquire`` returns the next image, raises :class:`NotReady` when there is none yet
    (it must not block for long: the server's health answers between calls), raises
    :class:`SourceUnavailable` when the instrument fails, and returns None when the
    source has ended for good (a replay played once).
    """

    name: str

    def acquire(self) -> AcquiredImage | None: ...

    def describe(self) -> dict: ...

    def close(self) -> None: ...


class ImageSourceAdapter(abc.ABC):
    """Base class for a lab's own image source (an SEM vendor's API).

    Made with the options of ``imageserver.adapter_options`` as keyword arguments.
    Implement :meth:`acquire` (blocking for a scan is fine: the image server runs an
    adapter in a thread of its own, see ``blocking``). The optional capabilities raise
    :class:`NotSupported` until an adapter provides them; the image server then
    answers a request for them with a clear refusal.
    """

    name = "adapter"
    #: True when :meth:`acquire` blocks for a scan (most vendor APIs): the image
    #: server then acquires in a background thread and publishes the newest frame.
    blocking = True

    def __init__(self, **options: Any):
        self.options = options

    @abc.abstractmethod
    def acquire(self) -> AcquiredImage | None:
        """The next image (see :class:`ImageSource` for the contract)."""

    def describe(self) -> dict:
        return {"source": self.name, "adapter": f"{type(self).__module__}:{type(self).__qualname__}",
                "options": {key: str(value) for key, value in self.options.items()}}

    def close(self) -> None:
        """Release the instrument (the image server calls it once, at the end)."""

    # Optional capabilities ------------------------------------------------------------
    def set_scan(self, *, dwell_ns: float | None = None, magnification: float | None = None) -> dict:
        """Change scan settings for the frames that follow; returns what is now set."""
        raise NotSupported(f"{self.name} cannot change its scan settings")

    def set_working_distance(self, working_distance_mm: float) -> float:
        """Focus at this working distance (the tilt measurement sweeps it); returns the
        working distance now set. With it (and :meth:`working_distance`), the image
        server serves focus sweeps from this adapter (:meth:`scan_at_focus`)."""
        raise NotSupported(f"{self.name} cannot set the focus")

    def working_distance(self) -> float:
        """The working distance (mm) the instrument is focused at now. Optional: without
        it, a focus sweep is centred on the working distance of the last frame."""
        raise NotSupported(f"{self.name} does not say its working distance")

    def capabilities(self) -> set[str]:
        """What this adapter can do beyond acquiring: ``scan_settings``, ``focus``.
        Found from what the class implements, so an adapter states nothing twice."""
        found = set()
        if type(self).set_scan is not ImageSourceAdapter.set_scan:
            found.add("scan_settings")
        if type(self).set_working_distance is not ImageSourceAdapter.set_working_distance:
            found.add("focus")
        return found

    def scan_at_focus(self, offset_um: float, nominal_mm: float) -> AcquiredImage:
        """One frame focused ``offset_um`` (um, larger deeper) from ``nominal_mm``: a
        frame of a focus sweep (the image server pauses the stream meanwhile, and sets
        the focus back to ``nominal_mm`` when the sweep ends)."""
        self.set_working_distance(nominal_mm + offset_um / 1000.0)
        image = self.acquire()
        if image is None:
            raise SourceUnavailable(f"{self.name} ended during a focus sweep")
        return image


# -- stage drivers -------------------------------------------------------------------------
class LinkError(RuntimeError):
    """The link to the instrument failed: the port is gone, or it did not answer in time."""


class DeviceError(ValueError):
    """The instrument refused a command (its protocol's error reply)."""


@dataclass(frozen=True)
class LogEntry:
    """One line exchanged with an instrument, for the run records."""

    time_ns: int
    direction: str  # "sent" or "received"
    text: str


@runtime_checkable
class StageDriver(Protocol):
    """One amplifier or controller whose numbered channels drive the stage's axes.

    Outputs are in the driver's unit (volts for a piezo amplifier); the stage service
    turns micrometres into outputs through each axis's model and checks every rule
    before a value reaches :meth:`write_outputs`. Methods raise :class:`LinkError` when
    the link fails and :class:`DeviceError` for a command it refuses; every
    line exchanged is appended to ``log`` and passed to ``on_entry`` when it is set.
    """

    log: list[LogEntry]
    on_entry: Callable[[LogEntry], None] | None

    @classmethod
    def open(cls, url: str) -> "StageDriver": ...

    def identify(self) -> dict:
        """What the device says it is (``{"model": ...}``), checking that it answers."""

    def take_control(self, channels: list[int]) -> None:
        """Command these channels from the computer (not a front panel)."""

    def release(self, channels: list[int]) -> None:
        """Give these channels back to the front panel."""

    def output_limits(self) -> tuple[float, float]:
        """The device's own output range."""

    def read_outputs(self) -> dict[int, float]:
        """What every channel outputs now (measured, not what was asked)."""

    def write_outputs(self, values: dict[int, float]) -> dict[int, float]:
        """Set these channels; return every channel's output read back afterwards."""

    def halt(self) -> None:
        """Stop any motion in progress (an amplifier holds its outputs: nothing to do)."""

    def close(self) -> None: ...


@runtime_checkable
class RotationStageDriver(Protocol):
    """A rotation-and-tilt stage: rotation about the beam and two tilts, in degrees, by
    axis name (``rotation_deg``, ``tilt_x_deg``, ``tilt_y_deg``: the ones it has).

    The stage service checks every rule (state, owner, finite values, travel, step)
    before :meth:`move_to` is called. Methods raise :class:`LinkError` when the link
    fails and :class:`DeviceError` for a command the device refuses.
    """

    def travel(self) -> dict[str, tuple[float, float]]:
        """Each axis's travel (degrees), as the device reports or documents it."""

    def read_angles(self) -> dict[str, float]:
        """Where every axis is now."""

    def move_to(self, angles: dict[str, float]) -> dict[str, float]:
        """Start moving these axes; return every axis's angle now (a stage that moves at
        a finite speed is still on its way: see :meth:`settles_in_s`)."""

    def settles_in_s(self) -> float:
        """Seconds (wall clock) until the last move has arrived; 0 when still. The
        stage service tells the controller, which treats frames scanned before then as
        stale. Optional: a driver without it is taken to arrive at once."""

    def halt(self) -> None:
        """Stop any motion in progress."""

    def close(self) -> None: ...


# -- motion drivers (physical units) ---------------------------------------------------------
#: A driver's kind (:func:`driver_kind`): ``voltage`` outputs through each axis's
#: displacement-voltage model (:class:`StageDriver`), or ``physical`` axes that take
#: micrometres and degrees themselves (:class:`MotionDriver`).
VOLTAGE, PHYSICAL = "voltage", "physical"


@dataclass(frozen=True)
class Axis:
    """One axis of a :class:`MotionDriver`, as the device reports or documents it.

    ``unit`` is ``um`` (a translation in the image plane) or ``deg`` (a turn or tilt).
    ``moves`` says what moves: the ``stage`` (the sample) or the ``beam`` (the scanned
    field, a beam shift: small travel, no mechanics). ``travel`` is the axis's range in
    the device's own coordinates (absolute positions). A beam axis moves the content the
    way the stage axis of the same letter does (``beam_x`` as ``x``): its driver makes
    that so, so a run can hand the last micrometres from one to the other."""

    unit: str = "um"
    moves: str = "stage"
    travel: tuple[float, float] = (-math.inf, math.inf)


@runtime_checkable
class MotionDriver(Protocol):
    """Axes that take displacements in physical units (:class:`Axis`: micrometres or
    degrees) and report their position: a closed-loop stage, a microscope's own stage,
    its beam shift.

    The stage service checks every rule (state, owner, finite, the axis's travel, its
    step per command) before :meth:`move_by` is called, and compares what it reads back
    with what it commanded. Methods raise :class:`LinkError` when the link fails and
    :class:`DeviceError`, in the device's own words, for a command it refuses (a move
    out of its range, a shift beyond its limit: never clipped in silence). Every command
    sent is appended to ``log`` (and passed to ``on_entry``) for the run records.
    """

    #: :data:`PHYSICAL`: how the stage service and the controller tell it from a
    #: :class:`StageDriver`.
    kind: str
    log: list[LogEntry]
    on_entry: Callable[[LogEntry], None] | None

    @classmethod
    def open(cls, url: str) -> "MotionDriver": ...

    def identify(self) -> dict:
        """What the device says it is (``{"model": ...}``), checking that it answers."""

    def axes(self) -> dict[str, Axis]:
        """Every axis, by name: ``x``, ``y`` (um), ``beam_x``, ``beam_y`` (um),
        ``rotation_deg``, ``tilt_x_deg`` (degrees), the ones it has."""

    def read_positions(self) -> dict[str, float]:
        """Where every axis is now (measured, not what was asked)."""

    def move_by(self, steps: dict[str, float]) -> dict[str, float]:
        """Move these axes by these displacements; return every axis's position read
        back afterwards (a stage on its way: see :meth:`settles_in_s`)."""

    def settles_in_s(self) -> float:
        """Seconds (wall clock) until the last move has arrived; 0 when still.
        Optional: a driver without it arrives at once (the stage service adds each
        axis's ``settle_s``)."""

    def halt(self) -> None:
        """Stop any motion in progress."""

    def close(self) -> None: ...


def driver_kind(driver: Any) -> str:
    """:data:`PHYSICAL` for a motion driver (its ``kind``), :data:`VOLTAGE` for an
    amplifier's stage driver (which has no ``kind``): a driver class or an instance."""
    return PHYSICAL if getattr(driver, "kind", VOLTAGE) == PHYSICAL else VOLTAGE


# -- finding what a lab wrote --------------------------------------------------------------
class PluginError(ValueError):
    """A named adapter or driver that cannot be loaded (the reason says why)."""


def load_plugin(spec: str, group: str) -> type:
    """The class named by ``spec``: an entry point of ``group``, or a dotted path
    ``package.module:ClassName`` (also ``package.module.ClassName``)."""
    for entry_point in importlib.metadata.entry_points(group=group):
        if entry_point.name == spec:
            try:
                return entry_point.load()
            except Exception as error:  # noqa: BLE001 - a lab's package may fail any way; say which
                raise PluginError(f"entry point {spec!r} of {group} fails to load: "
                                  f"{type(error).__name__}: {error}") from None
    module_name, sep, class_name = spec.partition(":")
    if not sep:
        module_name, _, class_name = spec.rpartition(".")
    if not module_name or not class_name:
        known = sorted(entry.name for entry in importlib.metadata.entry_points(group=group))
        raise PluginError(f"{spec!r} is neither a known name ({', '.join(known) or 'none'}) nor a dotted path "
                          f"'package.module:ClassName'")
    try:
        module = importlib.import_module(module_name)
    except ImportError as error:
        raise PluginError(f"cannot import {module_name!r} for {spec!r}: {error}") from None
    try:
        return getattr(module, class_name)
    except AttributeError:
        raise PluginError(f"{module_name!r} has no {class_name!r} (from {spec!r})") from None

