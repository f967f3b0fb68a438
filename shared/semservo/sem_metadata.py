"""What an SEM image file says about its acquisition, from the vendors' own tags.

Every field is in one unit (nanometres, millimetres, nanoseconds, kilovolts) whatever
the vendor wrote, and a field the file does not carry stays ``None``: a missing pixel
size is never replaced by a guess here (the user sets it; see ``imageserver.*``).

Read from:

* **Thermo Fisher / FEI** (tags 34680/34682, parsed by tifffile): ``[Scan] PixelWidth``,
  ``Dwelltime``; ``[Beam] HV``; ``[Stage] WorkingDistance``; ``[Detectors] Name``;
  ``[Image] ResolutionY`` (the image area; rows below it are the data bar).
* **Zeiss SmartSEM** (tag 34118, parsed by tifffile): ``ap_image_pixel_size``, ``ap_mag``,
  ``ap_wd``, ``ap_actualkv``, ``dp_detector_type``, ``dp_dwell_time``.
* **TESCAN** (tag 50431, an INI text after a thumbnail): ``PixelSizeX``, ``Magnification``,
  ``WD``, ``DwellTime``, ``HV``, ``Detector``, ``Device``, ``ImageStripSize`` (the data bar).
* **JEOL** (the companion text file beside the image, same name, ``.txt``):
  ``$CM_MAG``, ``$CM_ACCEL_VOLT``, ``$CM_SIGNAL``, ``$CM_INSTRUMENT``, ``$CM_WD``/``$SM_WD``,
  ``$$SM_MICRON_BAR`` with ``$$SM_MICRON_MARKER`` (pixel size), ``$CM_FULL_SIZE``.
* **Hitachi** (its companion ``.txt``, ``[SemImageFile]``): ``PixelSize``, ``Magnification``,
  ``WorkingDistance``, ``AcceleratingVoltage``, ``SignalName``, ``InstructName``, ``DataSize``.
* **ImageJ / Fiji** calibrations (``unit`` and XResolution): the pixel size.
* **semservo** itself: a JSON ``ImageDescription`` (``{"semservo": {...}}``) or PNG text
  chunks, with this module's field names.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: TIFF tags the vendors keep their metadata in.
TESCAN_TAG = 50431
FEI_TAGS = (34680, 34682)
ZEISS_TAG = 34118


@dataclass(frozen=True)
class ImageMetadata:
    """An SEM image's acquisition, as far as its file tells. ``None``: not known."""

    pixel_size_nm: float | None = None
    magnification: float | None = None
    working_distance_mm: float | None = None
    dwell_ns: float | None = None
    high_voltage_kv: float | None = None
    detector: str | None = None
    instrument: str | None = None
    #: Rows at the bottom that are the vendor's data bar, as the metadata says.
    data_bar_rows: int | None = None

    def known(self) -> dict[str, Any]:
        """The fields the file carries (what goes into a frame header)."""
        return {key: value for key, value in dataclasses.asdict(self).items() if value is not None}

    def updated(self, **fields: Any) -> "ImageMetadata":
        """These fields replaced where they are not None (user settings over the file)."""
        return dataclasses.replace(self, **{key: value for key, value in fields.items() if value is not None})


NUMBER_FIELDS = ("pixel_size_nm", "magnification", "working_distance_mm", "dwell_ns", "high_voltage_kv")
TEXT_FIELDS = ("detector", "instrument")


def _positive(value: Any, scale: float = 1.0) -> float | None:
    """A finite positive number times ``scale``, or None for anything else."""
    if isinstance(value, bool):
        return None
    try:
        number = float(str(value).strip()) * scale if isinstance(value, str) else float(value) * scale
    except (TypeError, ValueError):
        return None
    return number if math.isfinite(number) and number > 0 else None


def _text(value: Any) -> str | None:
    text = str(value).strip() if value is not None else ""
    return text[:200] or None


def from_fields(fields: dict[str, Any]) -> ImageMetadata:
    """semservo's own keys (a JSON description, PNG text chunks), flat or under ``"semservo"``."""
    if isinstance(fields.get("semservo"), dict):
        fields = fields["semservo"]
    found: dict[str, Any] = {key: _positive(fields.get(key)) for key in NUMBER_FIELDS}
    found.update({key: _text(fields.get(key)) for key in TEXT_FIELDS})
    rows = _positive(fields.get("data_bar_rows"))
    found["data_bar_rows"] = int(rows) if rows else None
    return ImageMetadata(**found)


def from_fei(sections: dict[str, dict[str, Any]], image_rows: int) -> ImageMetadata:
    """Thermo Fisher / FEI ``[Section] Key=value`` metadata (SI units in the file)."""
    def get(section: str, key: str) -> Any:
        return (sections.get(section) or {}).get(key)

    resolution_y = _positive(get("Image", "ResolutionY"))
    bar = int(image_rows - resolution_y) if resolution_y and image_rows > resolution_y else None
    return ImageMetadata(
        pixel_size_nm=_positive(get("Scan", "PixelWidth") or get("EScan", "PixelWidth"), 1e9),
        magnification=_positive(get("Image", "Magnification")),
        working_distance_mm=_positive(get("Stage", "WorkingDistance") or get("EBeam", "WD"), 1e3),
        dwell_ns=_positive(get("Scan", "Dwelltime") or get("EScan", "Dwell"), 1e9),
        high_voltage_kv=_positive(get("Beam", "HV") or get("EBeam", "HV"), 1e-3),
        detector=_text(get("Detectors", "Name")),
        instrument=_text(get("System", "SystemType") or get("System", "Type")),
        data_bar_rows=bar,
    )


_ZEISS_LENGTH_NM = {"pm": 1e-3, "nm": 1.0, "µm": 1e3, "um": 1e3, "mm": 1e6}
_ZEISS_TIME_NS = {"ns": 1.0, "µs": 1e3, "us": 1e3, "ms": 1e6, "s": 1e9}


def from_zeiss(entries: dict[str, Any]) -> ImageMetadata:
    """Zeiss SmartSEM: tifffile gives ``key -> (label, value[, unit])``."""
    def value(key: str) -> tuple[Any, str]:
        entry = entries.get(key)
        if not isinstance(entry, tuple) or len(entry) < 2:
            return None, ""
        return entry[1], (entry[2] if len(entry) > 2 else "")

    size, size_unit = value("ap_image_pixel_size")
    wd, wd_unit = value("ap_wd")
    dwell, dwell_unit = value("dp_dwell_time")
    kv, kv_unit = value("ap_actualkv")
    mag, _ = value("ap_mag")
    magnification = None
    if mag is not None:  # "50.00 K X", "1.50 M X" or a number
        match = re.match(r"\s*([0-9.]+)\s*([KM]?)\s*X?", str(mag), re.IGNORECASE)
        if match:
            magnification = _positive(match.group(1), {"": 1, "K": 1e3, "M": 1e6}[match.group(2).upper()])
    detector, _ = value("dp_detector_type")
    instrument, _ = value("sv_serial_number")
    return ImageMetadata(
        pixel_size_nm=_positive(size, _ZEISS_LENGTH_NM.get(size_unit or "nm", math.nan)),
        magnification=magnification,
        working_distance_mm=_positive(wd, _ZEISS_LENGTH_NM.get(wd_unit or "mm", math.nan) / 1e6),
        dwell_ns=_positive(dwell, _ZEISS_TIME_NS.get(dwell_unit or "ns", math.nan)),
        high_voltage_kv=_positive(kv, {"kV": 1.0, "V": 1e-3}.get(kv_unit or "kV", math.nan)),
        detector=_text(detector), instrument=_text(instrument),
    )


def _ini_pairs(text: str) -> dict[str, str]:
    pairs = {}
    for line in text.splitlines():
        key, sep, value = line.partition("=")
        if sep and key.strip() and not key.strip().startswith(("[", "#", ";")):
            pairs[key.strip()] = value.strip()
    return pairs


def from_tescan(raw: bytes) -> ImageMetadata:
    """TESCAN's tag 50431: a JPEG 2000 thumbnail, then ``Key=value`` lines in SI units."""
    text = "\n".join(match.group().decode("ascii", "replace")
                     for match in re.finditer(rb"[\x20-\x7e\r\n\t]{8,}", raw))
    pairs = _ini_pairs(text)
    strip = _positive(pairs.get("ImageStripSize"))
    return ImageMetadata(
        pixel_size_nm=_positive(pairs.get("PixelSizeX"), 1e9),
        magnification=_positive(pairs.get("Magnification")),
        working_distance_mm=_positive(pairs.get("WD"), 1e3),
        dwell_ns=_positive(pairs.get("DwellTime"), 1e9),
        high_voltage_kv=_positive(pairs.get("HV"), 1e-3),
        detector=_text(pairs.get("Detector")),
        instrument=_text(f"TESCAN {pairs['Device']}") if pairs.get("Device") else None,
        data_bar_rows=int(strip) if strip else None,
    )


_JEOL_MARKER = re.compile(r"([0-9.]+)\s*(nm|um|µm|mm)", re.IGNORECASE)


def from_jeol_text(text: str, image_rows: int) -> ImageMetadata:
    """JEOL's companion ``.txt`` (``$KEY value`` lines, kV and mm)."""
    pairs: dict[str, str] = {}
    for line in text.splitlines():
        key, _, value = line.strip().partition(" ")
        if key.startswith("$"):
            pairs[key.lstrip("$").upper()] = value.strip()
    pixel_size = None
    bar_px = _positive(pairs.get("SM_MICRON_BAR"))
    marker = _JEOL_MARKER.match(pairs.get("SM_MICRON_MARKER", ""))
    if bar_px and marker:
        unit = {"nm": 1.0, "um": 1e3, "µm": 1e3, "mm": 1e6}[marker.group(2).lower()]
        pixel_size = _positive(marker.group(1), unit / bar_px)
    full = pairs.get("CM_FULL_SIZE", "").split()
    image_area_rows = _positive(full[1]) if len(full) == 2 else None
    bar = int(image_rows - image_area_rows) if image_area_rows and image_rows > image_area_rows else None
    return ImageMetadata(
        pixel_size_nm=pixel_size,
        magnification=_positive(pairs.get("CM_MAG")),
        working_distance_mm=_positive(pairs.get("CM_WD") or pairs.get("SM_WD")),
        high_voltage_kv=_positive(pairs.get("CM_ACCEL_VOLT")),
        detector=_text(pairs.get("CM_SIGNAL")),
        instrument=_text(f"JEOL {pairs['CM_INSTRUMENT']}") if pairs.get("CM_INSTRUMENT") else None,
        data_bar_rows=bar,
    )


_HITACHI_VALUE = re.compile(r"\s*([-+0-9.eE]+)\s*([A-Za-zµ]*)")


def from_hitachi_text(text: str, image_rows: int) -> ImageMetadata:
    """Hitachi's companion ``.txt`` (``[SemImageFile]``, ``Key=value unit`` lines)."""
    pairs = _ini_pairs(text)

    def value(key: str, units: dict[str, float], default_unit: str) -> float | None:
        match = _HITACHI_VALUE.match(pairs.get(key, ""))
        if not match:
            return None
        return _positive(match.group(1), units.get(match.group(2) or default_unit, math.nan))

    size = pairs.get("DataSize", "").lower().split("x")
    image_area_rows = _positive(size[1]) if len(size) == 2 else None
    bar = int(image_rows - image_area_rows) if image_area_rows and image_rows > image_area_rows else None
    return ImageMetadata(
        pixel_size_nm=value("PixelSize", {"nm": 1.0, "um": 1e3, "µm": 1e3}, "nm"),
        magnification=_positive(pairs.get("Magnification")),
        working_distance_mm=value("WorkingDistance", {"um": 1e-3, "µm": 1e-3, "mm": 1.0}, "um"),
        high_voltage_kv=value("AcceleratingVoltage", {"Volt": 1e-3, "V": 1e-3, "kV": 1.0}, "Volt"),
        detector=_text(pairs.get("SignalName")),
        instrument=_text(f"Hitachi {pairs['InstructName']}") if pairs.get("InstructName") else None,
        data_bar_rows=bar,
    )


_IMAGEJ_UNIT_NM = {"nm": 1.0, "nanometer": 1.0, "um": 1e3, "µm": 1e3, "micron": 1e3, "microns": 1e3,
                   "mm": 1e6, "\\u00B5m": 1e3}


def from_imagej(imagej: dict, x_resolution: tuple[int, int] | None) -> ImageMetadata:
    """An ImageJ/Fiji-calibrated TIFF: pixels per ``unit`` in XResolution."""
    unit = _IMAGEJ_UNIT_NM.get(str(imagej.get("unit", "")).strip().lower())
    if unit is None or not x_resolution or not x_resolution[0]:
        return ImageMetadata()
    return ImageMetadata(pixel_size_nm=_positive(x_resolution[1] / x_resolution[0], unit))


def from_tiff(tif, image_rows: int, path: Path | None) -> ImageMetadata:
    """Every source a TIFF may carry, the vendor's own first; ``tif`` is an open
    ``tifffile.TiffFile``."""
    page = tif.pages[0]
    if getattr(tif, "is_fei", False) and tif.fei_metadata:
        return from_fei(tif.fei_metadata, image_rows)
    if getattr(tif, "is_sem", False) and tif.sem_metadata:
        return from_zeiss(tif.sem_metadata)
    tescan = page.tags.get(TESCAN_TAG)
    if tescan is not None and isinstance(tescan.value, (bytes, bytearray)):
        return from_tescan(bytes(tescan.value))
    if path is not None:
        companion = path.with_suffix(".txt")
        if companion.is_file():
            text = companion.read_text(encoding="latin-1")
            if "[SemImageFile]" in text:
                return from_hitachi_text(text, image_rows)
            return from_jeol_text(text, image_rows)
    if getattr(tif, "is_imagej", False) and tif.imagej_metadata:
        resolution = page.tags.get(282)  # XResolution: pixels per unit, as a fraction
        return from_imagej(tif.imagej_metadata, resolution.value if resolution is not None else None)
    description = page.description or ""
    if description.strip().startswith("{"):
        try:
            fields = json.loads(description)
        except json.JSONDecodeError:
            fields = {}
        if isinstance(fields, dict):
            return from_fields(fields)
    return ImageMetadata()
