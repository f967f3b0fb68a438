"""A real SEM image as the simulated lab's sample: try semservo on pictures of your own
samples before a session at the microscope.

The image becomes a :class:`semservo.simulation.scenes.Sample` like the built-in scenes
(a secondary-electron yield map and a height map, in micrometres on the sample), so the
simulated SEM images it with the same probe, defocus, raster, noise, levels, charging,
drift, vibration and tilts. What happens to the picture on the way:

* **Read** with :func:`semservo.imagefiles.read_sem_image`: PNG or TIFF, 8 or 16 bit,
  vendor metadata, the data bar cropped.
* **Pixel size**: the file's (vendor tags), or the one given; an image without either is
  refused (the scale of the texture cannot be guessed).
* **Levels**: the image's own 0.5 and 99.5 percentiles become yields 0.1 and 0.9
  (:data:`YIELD_RANGE`), so an 8-bit picture and a 16-bit one that uses a sliver of its
  range look alike; the frames' bit depth is the scan's.
* **Its own noise**: the picture was acquired with noise, which would otherwise become
  frozen texture moving with the sample (flattering the registration) and have the
  simulator's noise added to it again. The noise is estimated (:func:`noise_sigma`, a
  robust median of the image's Laplacian-like residual) and removed by non-local means
  with a strength of ``denoise`` times it (OpenCV's ``fastNlMeansDenoising``; 0: kept).
* **Scale**: the sample is resampled to each scan's grid (half a scan pixel, as the
  built-in scenes). A scan coarser than the picture averages its pixels (area
  averaging, then cubic interpolation); a scan finer than the picture interpolates it
  (cubic): it shows the picture's detail, smooth between its pixels, never detail the
  picture does not have. A scan whose pixel is more than ``max_upsampling`` times finer
  than the picture's is refused, naming the highest magnification allowed.
* **Beyond the picture's edges** (the stage moves the sample, so the field sees past
  them): ``mirror`` (default: the picture reflected at its edges, continuous, no seam),
  ``tile`` (repeated: a seam, and a periodic scene), or ``pad`` (the picture's median
  yield, flat: nothing to register, as at a real sample's edge). A scan whose field is
  larger than ``max_field`` times the picture (either axis) is refused.
* **Height**: flat (0 um everywhere), or a second image of the same aspect ratio whose
  grey levels are heights: its darkest level 0, its brightest ``height_um`` (towards
  the lens), resampled and extended at the edges as the sample is.

The default scan of a sample image (its preset's magnification, see
:func:`semservo.simulation.world.image_preset`) has the picture's own pixel, or a finer
one where a 512 x 512 frame would not fit inside the picture (a picture under 512 px a
side is interpolated up a little).
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from semservo.config import SAMPLE_PIXEL_NM_RANGE, SCREEN_WIDTH_PX, SCREEN_WIDTH_UM, EstimatorSettings
from semservo.imagefiles import DataBar, ImageFileError, read_sem_image
from semservo.sem_metadata import ImageMetadata
from semservo.simulation.scenes import Sample

#: How the sample goes on beyond the picture's edges.
EDGES = ("mirror", "tile", "pad")
_BORDER = {"mirror": cv2.BORDER_REFLECT_101, "tile": cv2.BORDER_WRAP, "pad": cv2.BORDER_CONSTANT}
#: The picture's LEVEL_PERCENTILES become these secondary-electron yields.
LEVEL_PERCENTILES = (0.5, 99.5)
YIELD_RANGE = (0.1, 0.9)
#: Defaults of the options (the fake lab's settings repeat them).
DEFAULT_DENOISE = 1.5
DEFAULT_MAX_UPSAMPLING = 2.0
DEFAULT_MAX_FIELD = 1.0
#: The smallest picture accepted (either side, after the data bar): smaller has too
#: little texture to register and would be mostly mirrored copies.
MIN_SIDE_PX = 64
#: The raster a scan is rendered from covers at most this many fields (a stage that
#: moves further sees the raster reflected; the built-in scenes' +60 um of travel room
#: would be tens of fields on a high-magnification picture).
MAX_EXTENT_FIELDS = 3.0


class SampleImageError(ValueError):
    """A sample image that cannot be used, or a scan it cannot serve; the message says
    why and what to do."""


def noise_sigma(image: np.ndarray) -> float:
    """The white noise's standard deviation in ``image`` (its own units), estimated
    robustly: the median absolute response to the Laplacian-like mask of Immerkaer
    (1996), whose response to noise of deviation sigma has deviation 6 sigma, over
    0.6745 (a Gaussian's median absolute value). Edges and texture are a minority of
    the responses, so the median sees the noise. Underestimates in images that are
    mostly clipped flat (their residual is zero there)."""
    mask = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    response = cv2.filter2D(np.asarray(image, np.float32), -1, mask, borderType=cv2.BORDER_REFLECT)[1:-1, 1:-1]
    return float(np.median(np.abs(response)) / 0.6745 / 6.0)


def denoise(yield_map: np.ndarray, sigma: float, strength: float) -> np.ndarray:
    """Non-local means (OpenCV, 16-bit with the L1 norm) of a yield map in 0..1, with a
    filter strength of ``strength`` x ``sigma``; unchanged when either is 0."""
    if strength <= 0 or sigma <= 0:
        return yield_map.astype(np.float32, copy=True)
    levels = np.round(np.clip(yield_map, 0, 1) * 65535).astype(np.uint16)
    cleaned = cv2.fastNlMeansDenoising(levels, [float(strength * sigma * 65535)], None, 7, 21, cv2.NORM_L1)
    return cleaned.astype(np.float32) / 65535


def to_yield(pixels: np.ndarray) -> np.ndarray:
    """Grey levels as secondary-electron yield: the image's LEVEL_PERCENTILES become
    YIELD_RANGE, linearly, clipped to 0..1 (8 and 16 bit alike)."""
    values = np.asarray(pixels, np.float32)
    low, high = np.percentile(values, LEVEL_PERCENTILES)
    if not high > low:
        raise SampleImageError("the image is (almost all) one grey level: a blank picture has nothing to image")
    bottom, top = YIELD_RANGE
    return np.clip(bottom + (values - low) * ((top - bottom) / (high - low)), 0.0, 1.0).astype(np.float32)


def scan_pixel_um(magnification: float, cols: int) -> float:
    """The simulated SEM's pixel for a magnification (P = D / G, paper eq. 43)."""
    return SCREEN_WIDTH_UM / magnification * SCREEN_WIDTH_PX / cols


def magnification_for(pixel_um: float, cols: int) -> float:
    """The simulated SEM's magnification whose ``cols``-wide scan has ``pixel_um``."""
    return SCREEN_WIDTH_UM / pixel_um * SCREEN_WIDTH_PX / cols


@dataclass(frozen=True)
class SampleImage:
    """A picture prepared as a sample: yield (0..1, denoised) and height (um) on the
    picture's own pixel grid, centred on the sample's origin (the picture's centre is
    where the stage's home looks)."""

    name: str
    intensity: np.ndarray
    height_um: np.ndarray | None
    pixel_um: float
    edges: str = "mirror"
    max_upsampling: float = DEFAULT_MAX_UPSAMPLING
    max_field: float = DEFAULT_MAX_FIELD
    #: Where the pixel size came from: "metadata" or "setting".
    pixel_size_from: str = "setting"
    metadata: ImageMetadata = field(default_factory=ImageMetadata)
    noise_before: float = 0.0  # estimated noise (yield units) of the picture as read
    noise_after: float = 0.0  # and as used
    height_range_um: float = 0.0
    source_dtype: str = "float32"
    data_bar_rows: int = 0

    # -- building ------------------------------------------------------------------
    @classmethod
    def open(cls, path: str | Path, *, pixel_size_nm: float | None = None, data_bar: DataBar = "auto",
             height_image: str | Path | None = None, height_um: float | None = None, edges: str = "mirror",
             denoise_strength: float = DEFAULT_DENOISE, max_upsampling: float = DEFAULT_MAX_UPSAMPLING,
             max_field: float = DEFAULT_MAX_FIELD) -> "SampleImage":
        """The picture at ``path`` as a sample (see the module's text). ``pixel_size_nm``
        overrides the file's; without either the picture is refused."""
        path = Path(path)
        image = _read(path, data_bar, "sample image")
        metadata = image.metadata
        if pixel_size_nm is not None:
            pixel_from = "setting"
        elif metadata.pixel_size_nm is not None:
            pixel_size_nm, pixel_from = metadata.pixel_size_nm, "metadata"
        else:
            known = ", ".join(f"{key} {value}" for key, value in metadata.known().items()) or "nothing"
            raise SampleImageError(
                f"{path}: the file does not say its pixel size (its metadata: {known}); give it: "
                "--sample-pixel-nm NM (SEMSERVO_FAKELAB__SAMPLE_PIXEL_SIZE_NM), the sample's width per pixel")
        heights = None
        if height_image is not None:
            if height_um is None:
                raise SampleImageError(f"{height_image}: a height map needs the height of its brightest level over "
                                       "its darkest: --sample-height-um UM (SEMSERVO_FAKELAB__SAMPLE_HEIGHT_UM)")
            heights = _read(Path(height_image), data_bar, "height map").pixels
        return cls.from_array(image.pixels, pixel_size_nm / 1000, name=path.name, height_map=heights,
                              height_um=height_um, edges=edges, denoise_strength=denoise_strength,
                              max_upsampling=max_upsampling, max_field=max_field, pixel_size_from=pixel_from,
                              metadata=metadata, data_bar_rows=int(image.data_bar_rows))

    @classmethod
    def from_array(cls, pixels: np.ndarray, pixel_um: float, *, name: str = "array",
                   height_map: np.ndarray | None = None, height_um: float | None = None, edges: str = "mirror",
                   denoise_strength: float = DEFAULT_DENOISE, max_upsampling: float = DEFAULT_MAX_UPSAMPLING,
                   max_field: float = DEFAULT_MAX_FIELD, pixel_size_from: str = "setting",
                   metadata: ImageMetadata | None = None, data_bar_rows: int = 0) -> "SampleImage":
        """A grey-level array (any bit depth) with its pixel size (um) as a sample."""
        pixels = np.asarray(pixels)
        if pixels.ndim != 2:
            raise SampleImageError(f"{name}: a sample image is 2-D grey levels, got shape {pixels.shape}")
        if min(pixels.shape) < MIN_SIDE_PX:
            raise SampleImageError(f"{name}: {pixels.shape[1]} x {pixels.shape[0]} px is too small for a sample "
                                   f"(at least {MIN_SIDE_PX} px a side)")
        low_nm, high_nm = SAMPLE_PIXEL_NM_RANGE
        if not (math.isfinite(pixel_um) and low_nm <= pixel_um * 1000 <= high_nm):
            raise SampleImageError(f"{name}: the pixel size must be {low_nm:g}-{high_nm:g} nm (the finest SEMs resolve "
                                   f"about 0.1 nm), got {pixel_um * 1000!r} nm")
        if edges not in EDGES:
            raise SampleImageError(f"sample edges must be one of {', '.join(EDGES)}, got {edges!r}")
        if not max_upsampling >= 1:
            raise SampleImageError(f"max_upsampling must be at least 1, got {max_upsampling!r}")
        if not max_field > 0:
            raise SampleImageError(f"max_field must be positive, got {max_field!r}")
        if not denoise_strength >= 0:
            raise SampleImageError(f"the denoising strength must be 0 or more, got {denoise_strength!r}")
        if not np.all(np.isfinite(pixels)):
            raise SampleImageError(f"{name}: the image has NaN or infinite pixels")
        try:
            yield_map = to_yield(pixels)
        except SampleImageError as error:
            raise SampleImageError(f"{name}: {error}") from None
        noise_before = noise_sigma(yield_map)
        intensity = denoise(yield_map, noise_before, denoise_strength)
        heights = None
        height_range = 0.0
        if height_map is not None:
            heights, height_range = _heights(np.asarray(height_map), pixels.shape, height_um, name)
        return cls(name=name, intensity=intensity, height_um=heights, pixel_um=float(pixel_um), edges=edges,
                   max_upsampling=float(max_upsampling), max_field=float(max_field), pixel_size_from=pixel_size_from,
                   metadata=metadata or ImageMetadata(), noise_before=noise_before,
                   noise_after=noise_sigma(intensity), height_range_um=height_range, source_dtype=str(pixels.dtype),
                   data_bar_rows=data_bar_rows)

    # -- what it can be scanned at -----------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        return self.intensity.shape

    @property
    def size_um(self) -> tuple[float, float]:
        """The picture's width and height on the sample (um)."""
        rows, cols = self.shape
        return cols * self.pixel_um, rows * self.pixel_um

    @property
    def median_height_um(self) -> float:
        return float(np.median(self.height_um)) if self.height_um is not None else 0.0

    def coarsest_pixel_um(self, rows: int = SCREEN_WIDTH_PX, cols: int = SCREEN_WIDTH_PX) -> float:
        """The largest scan pixel whose ``rows`` x ``cols`` field fits inside ``max_field``
        times the picture."""
        height, width = self.shape
        return self.pixel_um * self.max_field * min(width / cols, height / rows)

    def default_pixel_um(self, rows: int = SCREEN_WIDTH_PX, cols: int = SCREEN_WIDTH_PX) -> float:
        """The scan pixel by default: the picture's own, or finer where a ``rows`` x
        ``cols`` frame would not fit inside ``max_field`` times the picture."""
        return min(self.pixel_um, self.coarsest_pixel_um(rows, cols))

    def default_magnification(self, rows: int = SCREEN_WIDTH_PX, cols: int = SCREEN_WIDTH_PX) -> float:
        return magnification_for(self.default_pixel_um(rows, cols), cols)

    def magnification_range(self, rows: int = SCREEN_WIDTH_PX, cols: int = SCREEN_WIDTH_PX) -> tuple[float, float]:
        """The lowest and highest magnification a ``rows`` x ``cols`` scan may have (the
        lowest above the highest: the picture is too small for such a scan)."""
        return (magnification_for(self.coarsest_pixel_um(rows, cols), cols),
                magnification_for(self.pixel_um / self.max_upsampling, cols))

    def check_scan(self, magnification: float, rows: int, cols: int) -> None:
        """Refuse (SampleImageError) a scan finer than ``max_upsampling`` allows or with a
        field larger than ``max_field`` times the picture."""
        pixel = scan_pixel_um(magnification, cols)
        low, high = self.magnification_range(rows, cols)
        width, height = self.size_um
        if low > high * (1 + 1e-9):
            raise SampleImageError(
                f"the sample image {self.name} ({self.shape[1]} x {self.shape[0]} px) is too small for a {cols} x "
                f"{rows} scan: its field would need the picture interpolated more than {self.max_upsampling:g} times "
                "(SEMSERVO_FAKELAB__SAMPLE_MAX_UPSAMPLING) or a field beyond the picture "
                "(SEMSERVO_FAKELAB__SAMPLE_MAX_FIELD); use a larger picture or scan fewer pixels")
        if pixel < self.pixel_um / self.max_upsampling * (1 - 1e-9):
            raise SampleImageError(
                f"a x{magnification:g} scan has {pixel * 1000:.4g} nm pixels, {self.pixel_um / pixel:.3g} times finer "
                f"than the sample image {self.name}'s {self.pixel_um * 1000:.4g} nm: the picture has no such detail "
                f"(interpolated up to {self.max_upsampling:g} times, SEMSERVO_FAKELAB__SAMPLE_MAX_UPSAMPLING); "
                f"scan at x{high:.4g} or less, or use a picture taken at a higher magnification")
        if cols * pixel > self.max_field * width * (1 + 1e-9) or rows * pixel > self.max_field * height * (1 + 1e-9):
            raise SampleImageError(
                f"a {cols} x {rows} scan at x{magnification:g} spans {cols * pixel:.4g} x {rows * pixel:.4g} um, larger "
                f"than {self.max_field:g} times the sample image {self.name} ({width:.4g} x {height:.4g} um, "
                f"SEMSERVO_FAKELAB__SAMPLE_MAX_FIELD); scan at x{low:.4g} or more")

    def extent_um(self, field_um: float) -> float:
        """The side of the raster a scan of ``field_um`` is rendered from: room for the
        start offsets, stage travel and drift (as the built-in scenes), at most
        MAX_EXTENT_FIELDS fields."""
        return min(max(2.2 * field_um, field_um + 60.0), MAX_EXTENT_FIELDS * field_um)

    # -- rendering ------------------------------------------------------------------
    def rasterize(self, pixel_um: float, extent_um: float) -> Sample:
        """The sample on a square grid of ``pixel_um`` covering ``extent_um`` centred on
        the origin (what :class:`semservo.simulation.sem.SEM` renders from), the picture
        extended beyond its edges as ``edges`` says."""
        size = int(np.ceil(extent_um / pixel_um))
        extent_um = size * pixel_um
        intensity = self._resample(self.intensity, pixel_um, size, float(np.median(self.intensity)))
        if self.height_um is None:
            height = np.zeros((size, size), np.float32)
        else:
            height = self._resample(self.height_um, pixel_um, size, self.median_height_um)
        return Sample(f"image:{self.name}", intensity, height, pixel_um, extent_um)

    def _resample(self, image: np.ndarray, pixel_um: float, size: int, pad_value: float) -> np.ndarray:
        rows, cols = image.shape
        scale_x = scale_y = self.pixel_um
        source = image
        if pixel_um > self.pixel_um:  # coarser than the picture: average its pixels first
            factor = pixel_um / self.pixel_um
            new_cols, new_rows = max(1, round(cols / factor)), max(1, round(rows / factor))
            source = cv2.resize(image, (new_cols, new_rows), interpolation=cv2.INTER_AREA)
            scale_x, scale_y = cols * self.pixel_um / new_cols, rows * self.pixel_um / new_rows
        source_rows, source_cols = source.shape
        # Grid pixel (c, r) lies at x = (c + 0.5) pixel - extent / 2 um; the source pixel
        # (j, i) at (j - (cols - 1) / 2) scale_x: the picture is centred on the origin.
        half = size * pixel_um / 2
        matrix = np.array([[pixel_um / scale_x, 0.0, (0.5 * pixel_um - half) / scale_x + (source_cols - 1) / 2],
                           [0.0, pixel_um / scale_y, (0.5 * pixel_um - half) / scale_y + (source_rows - 1) / 2]])
        return cv2.warpAffine(source, matrix, (size, size), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                              borderMode=_BORDER[self.edges], borderValue=float(pad_value)).astype(np.float32)

    def describe(self) -> dict:
        """What the fake lab says about its sample (``info``)."""
        width, height = self.size_um
        low, high = self.magnification_range()
        return {"name": self.name, "shape": list(self.shape), "pixel_size_nm": self.pixel_um * 1000,
                "pixel_size_from": self.pixel_size_from, "size_um": [width, height], "edges": self.edges,
                "source_dtype": self.source_dtype, "data_bar_rows": self.data_bar_rows,
                "noise_yield": {"as_read": self.noise_before, "as_used": self.noise_after},
                "height_um": self.height_range_um if self.height_um is not None else None,
                "default_magnification": self.default_magnification(), "magnification_range": [low, high],
                "max_upsampling": self.max_upsampling, "max_field": self.max_field}


def _read(path: Path, data_bar: DataBar, what: str):
    if path.is_dir():
        raise SampleImageError(f"{path}: a folder, not a {what} file")
    if not path.is_file():
        raise SampleImageError(f"{path}: no such {what} file")
    try:
        return read_sem_image(path, data_bar=data_bar)
    except ImageFileError as error:
        raise SampleImageError(f"cannot read the {what} as a grey-level PNG/TIFF: {error}") from None


def _heights(height_map: np.ndarray, shape: tuple[int, int], height_um: float | None,
             name: str) -> tuple[np.ndarray, float]:
    """A height map's grey levels as heights (um): darkest 0, brightest ``height_um``,
    resized to the picture when it has the same aspect ratio."""
    if height_map.ndim != 2:
        raise SampleImageError(f"{name}: the height map must be 2-D grey levels, got shape {height_map.shape}")
    if height_um is None or not (math.isfinite(height_um) and height_um > 0):
        raise SampleImageError(f"{name}: the height map needs a positive height of its brightest level (um), "
                               f"got {height_um!r}")
    rows, cols = shape
    map_rows, map_cols = height_map.shape
    if abs(map_cols / map_rows - cols / rows) > 0.01 * cols / rows:
        raise SampleImageError(f"{name}: the height map is {map_cols} x {map_rows} px, the picture {cols} x {rows}: "
                               "they must show the same field (the same aspect ratio)")
    values = np.asarray(height_map, np.float32)
    unusable = int(np.count_nonzero(~np.isfinite(values)))
    if unusable:
        raise SampleImageError(f"{name}: its height map has {unusable} NaN or infinite pixels (of {values.size}); "
                               "every pixel needs a height")
    low, high = float(values.min()), float(values.max())
    heights = np.zeros_like(values) if high <= low else (values - low) * (height_um / (high - low))
    if heights.shape != shape:
        heights = cv2.resize(heights, (cols, rows), interpolation=cv2.INTER_AREA if map_cols > cols else cv2.INTER_CUBIC)
    return heights.astype(np.float32), float(height_um)


# -- the options, one definition for `semservo fakelab`, `up` and `demo` ----------------

#: Command-line option -> the fake lab's setting it sets (SEMSERVO_FAKELAB__...).
OPTION_SETTINGS = {
    "sample_image": "SAMPLE_IMAGE", "sample_pixel_nm": "SAMPLE_PIXEL_SIZE_NM", "sample_data_bar": "SAMPLE_DATA_BAR",
    "sample_height_image": "SAMPLE_HEIGHT_IMAGE", "sample_height_um": "SAMPLE_HEIGHT_UM",
    "sample_edges": "SAMPLE_EDGES", "sample_denoise": "SAMPLE_DENOISE",
    "sample_max_upsampling": "SAMPLE_MAX_UPSAMPLING", "sample_max_field": "SAMPLE_MAX_FIELD",
}


def _number(low: float, high: float, *, above: bool = False):
    """An option's number type: finite, from ``low`` (or above it) to ``high``; argparse
    names the option in its error."""
    def number(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        if not (math.isfinite(value) and (value > low if above else value >= low) and value <= high):
            raise argparse.ArgumentTypeError(f"must be a number {'above' if above else 'from'} {low:g} up to "
                                             f"{high:g}, got {text!r}")
        return value
    return number


def _data_bar(text: str) -> str:
    if text == "auto" or (text.isdigit() and int(text) <= 100_000):
        return text
    raise argparse.ArgumentTypeError(f"must be auto or a number of rows from 0 up to 100000, got {text!r}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The sample-image options (each also a SEMSERVO_FAKELAB__SAMPLE_* setting; the
    ranges are the settings')."""
    group = parser.add_argument_group(
        "sample image", "a real SEM image (PNG/TIFF, 8/16 bit) as the simulated lab's sample, imaged like the "
                        "built-in scenes (semservo.simulation.sample_image)")
    group.add_argument("--sample-image", metavar="FILE", help="the picture to use as the sample (data bar cropped)")
    group.add_argument("--sample-pixel-nm", type=_number(*SAMPLE_PIXEL_NM_RANGE), metavar="NM",
                       help="its pixel size on the sample, nm (default: the file's metadata; required without)")
    group.add_argument("--sample-data-bar", type=_data_bar, metavar="ROWS",
                       help="rows of data bar to crop: auto (default) or a number")
    group.add_argument("--sample-height-image", metavar="FILE",
                       help="a height map of the same field (brighter is higher); default: flat")
    group.add_argument("--sample-height-um", type=_number(0, 1e4, above=True), metavar="UM",
                       help="the height map's brightest level over its darkest, um (required with a height map)")
    group.add_argument("--sample-edges", choices=EDGES,
                       help="beyond the picture's edges: mirror (default), tile, or pad (flat median grey)")
    group.add_argument("--sample-denoise", type=_number(0, 10), metavar="K",
                       help=f"remove the picture's own noise, non-local means at K x its estimated deviation "
                            f"(default {DEFAULT_DENOISE:g}; 0: keep it)")
    group.add_argument("--sample-max-upsampling", type=_number(1, 100), metavar="K",
                       help=f"refuse scans more than K times finer than the picture (default {DEFAULT_MAX_UPSAMPLING:g})")
    group.add_argument("--sample-max-field", type=_number(0, 100, above=True), metavar="K",
                       help=f"refuse scans whose field exceeds K times the picture (default {DEFAULT_MAX_FIELD:g})")


def environment_from_arguments(args: argparse.Namespace) -> dict[str, str]:
    """The SEMSERVO_FAKELAB__SAMPLE_* settings the given options set (paths absolute, so
    child processes in another directory find them)."""
    variables = {}
    for option, setting in OPTION_SETTINGS.items():
        value = getattr(args, option, None)
        if value is None:
            continue
        if option in ("sample_image", "sample_height_image"):
            value = Path(value).expanduser().resolve()
        variables[f"SEMSERVO_FAKELAB__{setting}"] = str(value)
    return variables


def find_picture(name: str | Path) -> Path:
    """A picture's path: a file as given, or a name (with or without its suffix) in the
    real SEM images' folder (``../shared/data/sem-images``, ``SEMSERVO_SEM_IMAGES``)."""
    from semservo.config import find_sem_images

    path = Path(name)
    if path.is_file():
        return path.resolve()
    folder = find_sem_images()
    for candidate in (folder / str(name), folder / f"{name}.tif", folder / f"{name}.png"):
        if candidate.is_file():
            return candidate
    raise SampleImageError(f"no picture {str(name)!r}: not a file, nor a name in {folder}")


def from_settings(settings) -> SampleImage | None:
    """The fake lab's sample image from its settings (:class:`semservo.config.FakelabSettings`),
    or None without one."""
    if settings.sample_image is None:
        return None
    return SampleImage.open(settings.sample_image, pixel_size_nm=settings.sample_pixel_size_nm,
                            data_bar=settings.sample_data_bar, height_image=settings.sample_height_image,
                            height_um=settings.sample_height_um, edges=settings.sample_edges,
                            denoise_strength=settings.sample_denoise, max_upsampling=settings.sample_max_upsampling,
                            max_field=settings.sample_max_field)


def system_environment(settings) -> dict[str, str]:
    """The settings of the rest of the system that follow from the fake lab's sample
    image (``settings``: :class:`semservo.config.Settings`): the estimator's depth of
    field for the tilts' focus sweeps, 2 P / alpha at the scan's pixel P and the preset's
    beam half-angle alpha (a picture's scale is not the built-in scenes', so neither is
    the depth of field), and the working distance the first sweep is centred on (the
    picture's median height in focus). Empty without a sample image; opens the picture,
    so an unusable one raises SampleImageError here."""
    from semservo.simulation.sem import beam_half_angle
    from semservo.simulation.world import PRESETS

    sample = from_settings(settings.fakelab)
    preset = PRESETS.get(settings.fakelab.preset)
    if sample is None or preset is None:
        return {}
    rows = cols = SCREEN_WIDTH_PX
    magnification = settings.imageserver.scan_magnification or sample.default_magnification(rows, cols)
    sample.check_scan(magnification, rows, cols)
    pixel = scan_pixel_um(magnification, cols)
    aperture = settings.imageserver.scan_aperture_um or preset.aperture_um
    half_angle = beam_half_angle(aperture, preset.working_distance_mm)
    depth_of_field = 2 * pixel / half_angle
    largest = EstimatorSettings.model_fields["tilt_depth_of_field_um"].metadata
    largest_um = min(rule.le for rule in largest if getattr(rule, "le", None) is not None)
    if depth_of_field > largest_um:
        raise SampleImageError(
            f"the sample image {sample.name} scanned at {pixel * 1000:.4g} nm a pixel would have a depth of field of "
            f"{depth_of_field:.4g} um (2 P / the beam's half-angle {half_angle:.3g} rad), over the {largest_um:g} um "
            f"the tilts' sweeps can take: a scan pixel of at most {largest_um * half_angle / 2 * 1000:.4g} nm (is "
            "--sample-pixel-nm right? or scan at a higher magnification: SEMSERVO_IMAGESERVER__SCAN_MAGNIFICATION)")
    return {"SEMSERVO_ESTIMATOR__TILT_DEPTH_OF_FIELD_UM": f"{depth_of_field:.6g}",
            "SEMSERVO_ESTIMATOR__TILT_CENTRE_UM": f"{-sample.median_height_um + 0.0:.6g}"}
