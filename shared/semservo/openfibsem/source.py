"""An image source for a microscope through OpenFIBSEM: ``acquire_image`` with the scan
the settings ask for, and what the image's metadata says in every frame header.

From the settings (``SEMSERVO_IMAGESERVER__ADAPTER_OPTIONS``, or keyword arguments):
``resolution`` ([columns, rows], default [512, 512]), ``dwell_ns`` (default 1000),
``hfw_um`` (the horizontal field width, default 100), ``beam`` (``electron`` or
``ion``); the microscope: ``manufacturer`` and ``host`` (``Demo``, ``localhost``) and
``config`` (a fibsem microscope-configuration YAML). From each image: the pixel size
(``metadata.pixel_size``), the working distance, the high voltage, the detector, the
microscope's maker and model, the dwell it was scanned with.
"""

from __future__ import annotations

import time
from typing import Any, Callable

import numpy as np

from semservo.instruments import AcquiredImage, ImageSourceAdapter, NotSupported, SourceUnavailable
from semservo.openfibsem import session


class OpenFibsemSource(ImageSourceAdapter):
    """:class:`~semservo.instruments.ImageSourceAdapter` over ``FibsemMicroscope.acquire_image``."""

    name = "openfibsem"

    def __init__(self, *, manufacturer: str = "Demo", host: str = "localhost", config: str | None = None,
                 resolution: tuple[int, int] | list[int] = (512, 512), dwell_ns: float = 1000.0,
                 hfw_um: float = 100.0, beam: str = "electron", microscope: Any = None,
                 clock: Callable[[], float] | None = None):
        super().__init__(manufacturer=manufacturer, host=host, config=config, resolution=list(resolution),
                         dwell_ns=dwell_ns, hfw_um=hfw_um, beam=beam)
        session.require_fibsem()
        columns, rows = (int(value) for value in resolution)
        if not (16 <= columns <= 16384 and 16 <= rows <= 16384):
            raise ValueError(f"resolution must be [columns, rows] of 16..16384 each, got {list(resolution)}")
        if not 1.0 <= float(dwell_ns) <= 1e6:
            raise ValueError(f"dwell_ns must be 1..1e6 ns, got {dwell_ns}")
        if not 0.01 <= float(hfw_um) <= 1e5:
            raise ValueError(f"hfw_um must be 0.01..1e5 um, got {hfw_um}")
        self.resolution = (columns, rows)
        self.dwell_ns, self.hfw_um = float(dwell_ns), float(hfw_um)
        self.beam = session.beam_type(beam)
        #: A clock of the source's own (seconds; a simulated microscope's): each frame's
        #: ``source_interval_s`` is then its scan on it. None (a microscope): the frames'
        #: wall-clock times say it all.
        self.microscope = microscope if microscope is not None else session.connect(manufacturer, host, config)
        self.clock = clock or getattr(self.microscope, "semservo_clock", None)  # a SimulatedDemoFrames' clock
        self.scans = 0

    def image_settings(self):
        """fibsem's ImageSettings for the next scan."""
        from fibsem.structures import ImageSettings

        return ImageSettings(resolution=self.resolution, dwell_time=self.dwell_ns * 1e-9, hfw=self.hfw_um * 1e-6,
                             beam_type=self.beam, autocontrast=False, save=False)

    def acquire(self) -> AcquiredImage:
        settings = self.image_settings()
        started_ns, started_s = time.time_ns(), self.clock() if self.clock else None
        try:
            image = self.microscope.acquire_image(image_settings=settings)
        except Exception as error:  # noqa: BLE001 - the SDK fails its own ways; the image server retries
            raise SourceUnavailable(f"acquire_image failed: {type(error).__name__}: {error}") from None
        interval = (started_s, self.clock()) if self.clock else None
        self.scans += 1
        pixels = np.asarray(image.data)
        if pixels.dtype not in (np.uint8, np.uint16, np.float32):
            pixels = pixels.astype(np.float32)  # frames carry uint8, uint16 or float32
        return AcquiredImage(pixels=pixels, acquired_at_ns=time.time_ns(), scan_started_at_ns=started_ns,
                             source_interval_s=interval, label=f"{self.beam.name.lower()} {self.scans}",
                             **metadata_of(image, settings))

    def set_scan(self, *, dwell_ns: float | None = None, magnification: float | None = None) -> dict:
        if magnification is not None:
            raise NotSupported("OpenFIBSEM scans a horizontal field width, not a magnification: set hfw_um in the "
                               "adapter's options")
        if dwell_ns is not None:
            if not 1.0 <= dwell_ns <= 1e6:
                raise ValueError(f"dwell {dwell_ns:g} ns is outside 1..1e6 ns")
            self.dwell_ns = float(dwell_ns)
        return {"dwell_ns": self.dwell_ns}

    def set_working_distance(self, working_distance_mm: float) -> float:
        self.microscope.set_working_distance(working_distance_mm * 1e-3, self.beam)
        return self.working_distance()

    def working_distance(self) -> float:
        return float(self.microscope.get_working_distance(self.beam)) * 1e3

    def describe(self) -> dict:
        return {**super().describe(), "microscope": type(self.microscope).__name__}


def metadata_of(image: Any, settings: Any = None) -> dict:
    """A ``FibsemImage``'s acquisition as frame-header fields (:class:`AcquiredImage`);
    a field it does not carry stays None (unknown), never made up."""
    metadata = getattr(image, "metadata", None)
    fields: dict[str, Any] = {}
    if metadata is None:
        return fields
    pixel = getattr(metadata, "pixel_size", None)
    if pixel is not None and getattr(pixel, "x", None):
        fields["pixel_size_nm"] = float(pixel.x) * 1e9
    used = getattr(metadata, "image_settings", None) or settings
    if used is not None and getattr(used, "dwell_time", None):
        fields["dwell_ns"] = round(float(used.dwell_time) * 1e9, 6)  # metres and seconds back: no float dust
    state = getattr(metadata, "microscope_state", None)
    beam_type = getattr(used, "beam_type", None)
    beam_state = None
    if state is not None:
        beam_state = getattr(state, "ion_beam" if getattr(beam_type, "name", "") == "ION" else "electron_beam", None)
        detector = getattr(state, "ion_detector" if getattr(beam_type, "name", "") == "ION" else "electron_detector",
                           None)
        if detector is not None and getattr(detector, "type", None):
            fields["detector"] = " ".join(str(part) for part in (detector.type, detector.mode) if part)
    if beam_state is not None:
        if getattr(beam_state, "working_distance", None):
            fields["working_distance_mm"] = float(beam_state.working_distance) * 1e3
        if getattr(beam_state, "voltage", None):
            fields["high_voltage_kv"] = float(beam_state.voltage) / 1e3
    info = getattr(metadata, "system_info", None)
    if info is not None:
        instrument = " ".join(str(part) for part in (getattr(info, "manufacturer", None), getattr(info, "model", None))
                              if part)
        if instrument:
            fields["instrument"] = instrument[:200]
    return fields
