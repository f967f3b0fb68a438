"""Reading and writing SEM frames as PNG or TIFF, 8 or 16 bit, with their metadata.

Metadata travels inside the file: PNG text chunks, or the TIFF ImageDescription as a
JSON object. Keys understood: ``pixel_size_nm``, ``magnification``, ``dwell_ns``
(flat, or under a ``"semservo"`` key). Anything missing is left to the caller's
defaults.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import tifffile
from PIL import Image, PngImagePlugin

IMAGE_SUFFIXES = (".png", ".tif", ".tiff")
METADATA_KEYS = ("pixel_size_nm", "magnification", "dwell_ns")


class ImageFileError(ValueError):
    """A file that is not a readable grey-level frame."""


def _numbers(fields: dict[str, Any]) -> dict[str, float]:
    if isinstance(fields.get("semservo"), dict):
        fields = fields["semservo"]
    found = {}
    for key in METADATA_KEYS:
        if key in fields:
            try:
                value = float(fields[key])
            except (TypeError, ValueError):
                continue
            if value > 0:
                found[key] = value
    return found


def _grey(pixels: np.ndarray, path: Path) -> np.ndarray:
    if pixels.ndim == 3 and pixels.shape[-1] in (3, 4):
        # An RGB(A) screenshot of a grey image: all channels are equal; keep one.
        if not np.array_equal(pixels[..., 0], pixels[..., 1]):
            raise ImageFileError(f"{path}: colour image; SEM frames are grey-level")
        pixels = pixels[..., 0]
    if pixels.ndim != 2:
        raise ImageFileError(f"{path}: expected a 2-D grey image, got shape {pixels.shape}")
    if pixels.dtype not in (np.uint8, np.uint16, np.float32):
        if pixels.dtype.kind in "iu" and pixels.min() >= 0 and pixels.max() <= 65535:
            pixels = pixels.astype(np.uint16)
        else:
            raise ImageFileError(f"{path}: pixel type {pixels.dtype} is not 8/16-bit or float32")
    return np.ascontiguousarray(pixels)


def read_image(source: str | Path | bytes) -> tuple[np.ndarray, dict[str, float]]:
    """Pixels (uint8, uint16 or float32, 2-D) and the metadata of a PNG or TIFF, given
    as a path or as the file's bytes (an upload)."""
    if isinstance(source, (bytes, bytearray)):
        path, handle = Path("upload"), io.BytesIO(source)
        is_tiff = bytes(source[:4]) in (b"II*\x00", b"MM\x00*")
    else:
        path = Path(source)
        handle, is_tiff = path, path.suffix.lower() in (".tif", ".tiff")
    try:
        if is_tiff:
            with tifffile.TiffFile(handle) as tif:
                pixels = tif.asarray()
                description = tif.pages[0].description or ""
            try:
                fields = json.loads(description) if description.strip().startswith("{") else {}
            except json.JSONDecodeError:
                fields = {}
        else:
            with Image.open(handle) as image:
                image.load()
                fields = dict(getattr(image, "text", {}) or {})
                if image.mode in ("I;16", "I;16B", "I;16L"):
                    pixels = np.array(image, dtype=np.uint16)
                else:
                    pixels = np.array(image)
    except (OSError, ValueError, SyntaxError, tifffile.TiffFileError) as error:
        raise ImageFileError(f"{path}: unreadable image ({error})") from None
    return _grey(pixels, path), _numbers(fields)


def write_image(path: str | Path, pixels: np.ndarray, **metadata: float) -> Path:
    """Write a frame with its metadata, as PNG or TIFF by the file's suffix."""
    path = Path(path)
    if path.suffix.lower() in (".tif", ".tiff"):
        tifffile.imwrite(path, pixels, description=json.dumps({"semservo": metadata}), metadata=None)
    else:
        info = PngImagePlugin.PngInfo()
        for key, value in metadata.items():
            info.add_text(key, str(value))
        Image.fromarray(pixels).save(path, pnginfo=info)
    return path


def list_frames(folder: str | Path, pattern: str = "*") -> list[Path]:
    """The PNG/TIFF files of a folder whose names match ``pattern``, in name order."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"no folder of frames at {folder}")
    return sorted(path for path in folder.glob(pattern) if path.suffix.lower() in IMAGE_SUFFIXES and path.is_file())
