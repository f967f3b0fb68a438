"""Reading and writing SEM frames: PNG or TIFF, 8 or 16 bit, with their metadata.

TIFF is read with tifffile and its codecs (imagecodecs: LZW, deflate, packbits, JPEG...),
so vendor files open as they are: palette images through their grey colour map, and
multi-page files by page (the first by default). Metadata comes from the vendors' own
tags (:mod:`semservo.sem_metadata`); semservo writes its own as a JSON
``ImageDescription`` or PNG text chunks.

Data bars, the strip of text and scale bar that SEM software saves under (or over) the
image, are not sample, and the estimator must never register them. :func:`read_sem_image`
crops them: by default (``data_bar="auto"``) the number of rows the metadata gives, else
what :func:`find_data_bar` finds; a number the caller gives (``data_bar=ROWS``, or ``0``
for none) replaces both.
"""

from __future__ import annotations

import io
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import tifffile
from PIL import Image, PngImagePlugin

from semservo.sem_metadata import ImageMetadata, from_fields, from_tiff

IMAGE_SUFFIXES = (".png", ".tif", ".tiff")

#: How a caller asks for the data bar: "auto" (metadata, else detection), or a number
#: of rows to crop (0: none).
DataBar = Literal["auto"] | int

#: Detection bounds. A bar is at most this fraction of the height (the rest is sample).
DATA_BAR_MAX_FRACTION = 0.3
#: A separate bar: rows of one fill value (the bar's background), on average at least
#: half of each row (the rest is text and logos), ending where a row holds less than
#: FILL_ABOVE of it.
FILL_IN_BAR, FILL_ABOVE = 0.5, 0.2
#: Text written over the image (JEOL's style): rows within the bottom OVERLAY_BAND of the
#: height with at least OVERLAY_TEXT of their pixels at full scale, OVERLAY_ROWS of them.
OVERLAY_BAND, OVERLAY_TEXT, OVERLAY_ROWS = 0.12, 0.04, 6
OVERLAY_MARGIN = 2


class ImageFileError(ValueError):
    """A file that is not a readable grey-level frame."""


@dataclass(frozen=True)
class SemImage:
    """A frame as read from a file: sample pixels only, and what the file says."""

    pixels: np.ndarray
    metadata: ImageMetadata
    data_bar_rows: int  # cropped from the bottom
    file_shape: tuple[int, int]  # before the crop


def _palette_to_grey(indices: np.ndarray, colormap: np.ndarray | None, path: Path) -> np.ndarray:
    """A palette image through its colour map; SEM palettes are grey ramps."""
    if colormap is None:
        return indices
    colormap = np.asarray(colormap)
    if colormap.ndim != 2 or colormap.shape[0] != 3:
        raise ImageFileError(f"{path}: palette image with an unexpected colour map {colormap.shape}")
    red, green, blue = colormap
    if not (np.array_equal(red, green) and np.array_equal(green, blue)):
        raise ImageFileError(f"{path}: colour palette image; SEM frames are grey-level")
    if np.array_equal(red, np.arange(red.size) * 257):  # the identity ramp: indices are the levels
        return indices
    return red[indices].astype(np.uint16)


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


def find_data_bar(pixels: np.ndarray) -> int:
    """Rows at the bottom of ``pixels`` that are a data bar, by their look; 0 if none.

    Two layouts are recognised. A separate bar (TESCAN, FEI, Zeiss): the bottom rows
    share one exact fill value over at least half of each row, text aside, and the row
    above the bar holds little of it. Text over the image (JEOL): rows near the bottom
    with several per cent of their pixels at the full-scale value, which sample pixels
    rarely are; the crop starts just above the highest of them. Anything else is
    sample: an image without a bar loses no rows. The look can mislead (a dark, clipped
    sample at the very bottom); where it does, say the rows (``data_bar=ROWS``).
    """
    rows = pixels.shape[0]
    limit = int(rows * DATA_BAR_MAX_FRACTION)
    bottom = pixels[-1]
    values, counts = np.unique(bottom, return_counts=True)
    fill = values[counts.argmax()]
    if counts.max() >= FILL_IN_BAR * bottom.size:
        fill_per_row = (pixels[rows - limit:] == fill).mean(axis=1)[::-1]  # bottom row first
        height = int(np.argmax(fill_per_row < FILL_ABOVE)) if (fill_per_row < FILL_ABOVE).any() else limit
        if 0 < height < limit and fill_per_row[:height].mean() >= FILL_IN_BAR:
            return height
    if pixels.dtype.kind in "ui":
        full_scale = np.iinfo(pixels.dtype).max
        band = max(1, int(rows * OVERLAY_BAND))
        text_rows = np.flatnonzero((pixels[rows - band:] == full_scale).mean(axis=1) >= OVERLAY_TEXT)
        if text_rows.size >= OVERLAY_ROWS:
            return band - text_rows[0] + OVERLAY_MARGIN
    return 0


def _read_tiff(handle, path: Path | None, page: int) -> tuple[np.ndarray, ImageMetadata]:
    with tifffile.TiffFile(handle) as tif:
        if not 0 <= page < len(tif.pages):
            raise ImageFileError(f"{path}: no page {page}; the file has {len(tif.pages)}")
        tiff_page = tif.pages[page]
        ends = [offset + count for offset, count in zip(tiff_page.dataoffsets, tiff_page.databytecounts)]
        if ends and max(ends) > tif.filehandle.size:
            # A file still being written (or cut short): its pixels end past the end of the file.
            raise ImageFileError(f"{path or 'upload'}: truncated TIFF ({tif.filehandle.size} of {max(ends)} bytes)")
        pixels = tiff_page.asarray()
        if tiff_page.photometric == tifffile.PHOTOMETRIC.PALETTE:
            pixels = _palette_to_grey(pixels, tiff_page.colormap, path or Path("upload"))
        metadata = from_tiff(tif, pixels.shape[0], path)
    return pixels, metadata


def read_sem_image(source: str | Path | bytes, *, data_bar: DataBar = "auto", page: int = 0,
                   detected: dict[tuple[int, ...], int] | None = None) -> SemImage:
    """An SEM image file (a path, or the bytes of an upload) as sample pixels (uint8,
    uint16 or float32, 2-D, the data bar cropped) with its metadata.

    ``data_bar``: ``"auto"`` crops what the metadata says, else what
    :func:`find_data_bar` sees; a number crops that many rows (``0``: none).
    ``detected``: a stream's memory of what detection found per file shape (a replayed
    or watched folder's): the first frame of a shape decides for the frames after it, so
    a frame's height never changes mid-stream (detection cut a drifted frame's 5 blank
    rows, and every frame after a teach was refused for its size).
    """
    if isinstance(source, (bytes, bytearray)):
        path, handle = None, io.BytesIO(source)
        is_tiff = bytes(source[:4]) in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
    else:
        path = Path(source)
        handle, is_tiff = path, path.suffix.lower() in (".tif", ".tiff")
    name = path or Path("upload")
    try:
        if is_tiff:
            pixels, metadata = _read_tiff(handle, path, page)
        else:
            with Image.open(handle) as image:
                image.load()
                metadata = from_fields(dict(getattr(image, "text", {}) or {}))
                if image.mode == "P":
                    image = image.convert("L")
                pixels = np.array(image, dtype=np.uint16) if image.mode in ("I;16", "I;16B", "I;16L") else np.array(image)
    except ImageFileError:
        raise
    except (OSError, ValueError, SyntaxError, KeyError, IndexError, tifffile.TiffFileError) as error:
        # PIL names an upload by its buffer's repr ("<_io.BytesIO object at 0x...>"): say "the upload".
        said = re.sub(r"<_io\.BytesIO object at 0x[0-9a-fA-F]+>", "the upload", str(error))
        raise ImageFileError(f"{name}: unreadable image ({type(error).__name__}: {said})") from None
    pixels = _grey(pixels, name)
    if data_bar == "auto" and metadata.data_bar_rows is not None:
        crop = metadata.data_bar_rows
    elif data_bar == "auto" and detected is not None:
        if pixels.shape not in detected:
            detected[pixels.shape] = find_data_bar(pixels)
        crop = detected[pixels.shape]
    elif data_bar == "auto":
        crop = find_data_bar(pixels)
    elif isinstance(data_bar, int) and not isinstance(data_bar, bool) and data_bar >= 0:
        crop = data_bar
    else:
        raise ValueError(f"data_bar must be 'auto' or a number of rows >= 0, got {data_bar!r}")
    if crop >= pixels.shape[0]:
        raise ImageFileError(f"{name}: a data bar of {crop} rows leaves nothing of a {pixels.shape[0]}-row image")
    sample = np.ascontiguousarray(pixels[: pixels.shape[0] - crop]) if crop else pixels
    return SemImage(pixels=sample, metadata=metadata, data_bar_rows=crop, file_shape=pixels.shape)


def read_image(source: str | Path | bytes, *, data_bar: DataBar = "auto") -> tuple[np.ndarray, dict]:
    """Sample pixels and the known metadata fields of a PNG or TIFF (a path or an
    upload's bytes): :func:`read_sem_image` in a tuple."""
    image = read_sem_image(source, data_bar=data_bar)
    return image.pixels, image.metadata.known()


def write_image(path: str | Path, pixels: np.ndarray, **metadata) -> Path:
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
