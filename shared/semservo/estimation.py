"""Fourier-domain motion estimation between a taught reference and the current SEM image.

Implements section II-A to II-D of Marturi et al., "Image-Guided Nanopositioning Scheme
for SEM": rotation about the beam from the log-polar magnitude spectrum (eq. 9-12), then
sub-pixel translation from the normalized cross-power spectrum (eq. 18-24), with the
image SNR monitored (section II-D) and noisy frames filtered.

Small pure functions do each step; :class:`MotionEstimator` precomputes everything
that depends only on the reference (window, reference spectrum, log-polar reference,
FFT plans) once, and :meth:`MotionEstimator.estimate` runs the per-frame part.

Sign convention (a contract)
----------------------------
``dx``, ``dy`` are the displacement of the scene content in the current image relative
to the reference, in pixels, x along columns (right), y along rows (down): if
``current[y, x] == reference[y, x - 3]`` then ``dx == +3``. ``rotation_deg`` is positive
when the content turned counter-clockwise as displayed (row 0 at the top). With both,
the current image is the reference rotated by ``rotation_deg`` about the image centre
``((cols - 1) / 2, (rows - 1) / 2)`` and then shifted by ``(dx, dy)``.

Confidence
----------
``confidence`` in [0, 1] grades how clearly the translation peak stands out of the
correlation surface: it is a monotone map of the peak-to-sidelobe ratio
(PSR = (peak - sidelobe mean) / sidelobe std, the sidelobe being the surface outside an
11 x 11 box around the peak). Two unrelated images give a PSR near 5 (the largest of
M x N noise samples), so confidence is 0 up to PSR 6 and ``1 - exp(-(PSR - 6) / 8)``
beyond: 0.5 at PSR 11.5, 0.9 at PSR 24. Matching SEM frames score above 0.9; a
controller should refuse to move below about 0.5 (``MotionEstimator.min_confidence``).
"""

from __future__ import annotations

import logging
import os
import pickle
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
import pyfftw
from PIL import Image, ImageDraw

log = logging.getLogger(__name__)

MIN_SIZE = 64
#: Sidelobe exclusion half-width for the peak-to-sidelobe ratio (an 11 x 11 box).
PSR_EXCLUSION = 5
#: Below this SNR (dB) a frame is filtered with the 5 x 5 Gaussian (section II-D).
DEFAULT_SNR_THRESHOLD_DB = 15.0

cv2.setNumThreads(1)  # one core per estimate; the services parallelise across processes


# --------------------------------------------------------------------------------------
# Results


@dataclass(frozen=True)
class Motion:
    """Motion of the current image against the reference (see the module's convention)."""

    dx: float
    dy: float
    rotation_deg: float
    confidence: float
    snr_db: float
    #: Height of the normalized correlation peak (1 for identical images).
    peak: float = 0.0
    #: Peak-to-sidelobe ratio the confidence is computed from.
    psr: float = 0.0
    #: Whether the frame was below the SNR threshold and filtered.
    filtered: bool = False

    def as_dict(self) -> dict:
        return {
            "dx_px": self.dx,
            "dy_px": self.dy,
            "rotation_deg": self.rotation_deg,
            "confidence": self.confidence,
            "snr_db": self.snr_db,
            "peak": self.peak,
            "psr": self.psr,
            "filtered": self.filtered,
        }


# --------------------------------------------------------------------------------------
# Input checks


def as_image(image, name: str = "image") -> np.ndarray:
    """A finite 2-D float32 copy of ``image``; ValueError for anything else."""
    array = np.asarray(image)
    if array.size == 0:
        raise ValueError(f"{name} is empty")
    if array.ndim != 2:
        raise ValueError(f"{name} must be a 2-D grey image, got shape {array.shape}")
    if array.shape[0] < MIN_SIZE or array.shape[1] < MIN_SIZE:
        raise ValueError(f"{name} is {array.shape[1]} x {array.shape[0]}; at least {MIN_SIZE} x {MIN_SIZE} is needed")
    if array.dtype.kind not in "uif" and array.dtype != bool:
        raise ValueError(f"{name} has pixel type {array.dtype}; 8/16-bit integers or floats are expected")
    array = array.astype(np.float32, copy=True)
    if not np.isfinite(array).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    return array


# --------------------------------------------------------------------------------------
# Apodization


def apodization_window(shape: tuple[int, int], kind: str = "tukey", alpha: float = 0.5) -> np.ndarray:
    """Separable 2-D taper applied before the FFT (section II-A).

    The DFT treats the image as periodic, so its borders make a cross of spurious
    energy in the spectrum that correlates at zero shift. ``"hann"`` is the paper's
    window; ``"tukey"`` (flat over ``1 - alpha`` of each axis, Hann-shaped edges) keeps
    more of the image at full weight, which measured better on the real frames (see
    ``bench/estimator.py``); ``"blackman"`` tapers harder; ``"none"`` disables it.
    """
    rows, cols = shape

    def one_axis(length: int) -> np.ndarray:
        n = np.arange(length, dtype=np.float64)
        if kind == "hann":
            return 0.5 - 0.5 * np.cos(2 * np.pi * n / (length - 1))
        if kind == "blackman":
            return np.blackman(length)
        if kind == "tukey":
            taper = alpha * (length - 1) / 2
            weights = np.ones(length)
            rising = n < taper
            weights[rising] = 0.5 * (1 - np.cos(np.pi * n[rising] / taper))
            weights[::-1][rising] = weights[rising]
            return weights
        if kind == "none":
            return np.ones(length)
        raise ValueError(f"unknown window {kind!r}: hann, tukey, blackman or none")

    return np.outer(one_axis(rows), one_axis(cols)).astype(np.float32)


# --------------------------------------------------------------------------------------
# Noise (section II-D)


def estimate_snr_db(image: np.ndarray) -> float:
    """Single-image SNR in dB from the autocorrelation (Marturi et al., Scanning 2014).

    The zero-lag autocorrelation R(0) of the mean-free image holds signal plus noise
    power; pixel noise is uncorrelated from pixel to pixel, so the signal alone is the
    peak extrapolated from its neighbours, R_s(0) = (4 R(1) - R(2)) / 3 (a parabola
    through lags 1 and 2), averaged over the row and column directions. Noise power is
    R(0) - R_s(0).
    """
    # The central half of the rows holds plenty of pixels for the statistics and
    # halves the cost on the per-frame path.
    if image.shape[0] >= 4 * MIN_SIZE:
        quarter = image.shape[0] // 4
        image = image[quarter:-quarter]
    rows, cols = image.shape
    centred = np.ascontiguousarray(image - np.float32(image.mean(dtype=np.float64)), dtype=np.float32)
    flat = centred.ravel()
    zero_lag = float(np.dot(flat, flat)) / flat.size
    if zero_lag <= 0:
        return float("-inf")
    extrapolated = []
    for lag_sums in (
        # Down the columns: whole rows against rows `lag` below (contiguous views).
        [float(np.dot(flat[lag * cols:], flat[:-lag * cols])) / ((rows - lag) * cols) for lag in (1, 2)],
        # Along the rows: the flat array against itself moved by `lag`, minus the pairs
        # that straddle the end of one row and the start of the next.
        [
            (float(np.dot(flat[lag:], flat[:-lag]))
             - sum(float(np.dot(centred[:-1, cols - lag + k], centred[1:, k])) for k in range(lag)))
            / (rows * (cols - lag))
            for lag in (1, 2)
        ],
    ):
        lag1, lag2 = lag_sums
        extrapolated.append((4 * lag1 - lag2) / 3)
    signal = float(np.clip(np.mean(extrapolated), 1e-12 * zero_lag, zero_lag))
    noise = max(zero_lag - signal, 1e-12 * zero_lag)
    return float(10 * np.log10(signal / noise))


def gaussian_transfer(shape: tuple[int, int], size: int = 5, sigma: float = 1.0) -> np.ndarray:
    """DFT (real-input half plane) of the ``size`` x ``size`` Gaussian prefilter.

    With a normalized cross-power spectrum (eq. 18) a spatial prefilter of one image
    cancels out (its transfer function is real and positive), so the paper's 5 x 5
    Gaussian is applied where it acts: as a weight on the cross-power spectrum and the
    sub-pixel fit, which suppresses the noise-dominated high frequencies.
    """
    taps = np.arange(size) - size // 2
    kernel = np.exp(-0.5 * (taps / sigma) ** 2)
    kernel /= kernel.sum()
    rows, cols = shape
    fy = np.fft.fftfreq(rows)[:, None]
    fx = np.fft.rfftfreq(cols)[None, :]
    hy = (kernel[None, :] * np.cos(2 * np.pi * fy * taps[None, :])).sum(axis=1, keepdims=True)
    hx = (kernel[None, :] * np.cos(2 * np.pi * fx.T * taps[None, :])).sum(axis=1)[None, :]
    return (hy * hx).astype(np.float32)


def gaussian_lowpass(shape: tuple[int, int], sigma: float) -> np.ndarray:
    """Gaussian weight exp(-r^2 / 2 sigma^2) on the real-input half plane, r in
    cycles/pixel: band-limits the correlation against a mask reference."""
    v = np.fft.fftfreq(shape[0])[:, None]
    u = np.fft.rfftfreq(shape[1])[None, :]
    return np.exp(-0.5 * (u * u + v * v) / sigma**2).astype(np.float32)


# --------------------------------------------------------------------------------------
# Translation (section II-C)


def normalized_cross_power(current_spectrum: np.ndarray, reference_conjugate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalized cross-power spectrum Psi (eq. 18) and the magnitude it was divided by.

    The paper writes Psi = F conj(G) / |F conj(G)| for g(x) = f(x + dx); with our sign
    convention (content moved by +d) the same spectrum is G conj(F), whose inverse
    transform (eq. 19) peaks at +d.
    """
    cross = current_spectrum * reference_conjugate
    magnitude = np.abs(cross)
    return cross / np.maximum(magnitude, np.finfo(np.float32).tiny), magnitude


def _pairs(spectrum: np.ndarray) -> np.ndarray:
    """A complex64 array viewed as (..., 2) float32 (real, imaginary)."""
    return spectrum.view(np.float32).reshape(*spectrum.shape, 2)


def foroosh_subpixel(surface: np.ndarray, peak: tuple[int, int]) -> tuple[float, float]:
    """Sub-pixel peak offset (eq. 21-22, Foroosh et al. 2002), per axis.

    Around an integer peak C(0) the phase-correlation surface of a sub-pixel shift is a
    Dirichlet kernel; with C(s) the larger neighbour (s = +1 or -1, the sign of the
    neighbour), the offset is s * C(s) / (C(s) + C(0)). Falls back to 0 when the
    neighbours carry no information. Indices wrap around (the surface is periodic).
    """
    rows, cols = surface.shape
    peak_row, peak_col = peak
    centre = surface[peak_row, peak_col]
    offsets = []
    for before, after in (
        (surface[(peak_row - 1) % rows, peak_col], surface[(peak_row + 1) % rows, peak_col]),
        (surface[peak_row, (peak_col - 1) % cols], surface[peak_row, (peak_col + 1) % cols]),
    ):
        side, neighbour = (1.0, after) if after >= before else (-1.0, before)
        denominator = neighbour + centre
        offset = side * neighbour / denominator if neighbour > 0 and denominator > 0 else 0.0
        offsets.append(float(np.clip(offset, -0.5, 0.5)))
    return offsets[0], offsets[1]


def block_mean(image: np.ndarray, factor: int) -> np.ndarray:
    """Average ``factor`` x ``factor`` blocks (the image cropped to whole blocks)."""
    if factor == 1:
        return image
    rows, cols = image.shape[0] // factor, image.shape[1] // factor
    # INTER_AREA at a whole-number factor is the exact block mean, and much faster
    # than numpy's strided reshape-and-mean.
    return cv2.resize(image[: rows * factor, : cols * factor], (cols, rows), interpolation=cv2.INTER_AREA)


def shifted_window(window: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """``window`` moved by whole pixels (rows down, cols right), zero where it moved in.

    Weighting the current image with the reference's window moved along with the
    content makes both images weight the same scene points: a window fixed on the frame
    would weigh the moved content differently and bias the estimate towards zero shift.
    """
    moved = np.zeros_like(window)
    height, width = window.shape
    if abs(rows) >= height or abs(cols) >= width:
        return moved
    source_rows = slice(max(0, -rows), height - max(0, rows))
    source_cols = slice(max(0, -cols), width - max(0, cols))
    target_rows = slice(max(0, rows), height - max(0, -rows))
    target_cols = slice(max(0, cols), width - max(0, -cols))
    moved[target_rows, target_cols] = window[source_rows, source_cols]
    return moved


def centred_shift(index: float, length: int) -> float:
    """Wrap a peak index to a signed shift in [-length/2, length/2) (eq. 23-24)."""
    return index - length if index >= length / 2 else index


def peak_to_sidelobe(surface: np.ndarray, peak: tuple[int, int], exclusion: int = PSR_EXCLUSION) -> float:
    """(peak - sidelobe mean) / sidelobe std, the sidelobe excluding a box around the peak."""
    rows, cols = surface.shape
    row_index = np.arange(peak[0] - exclusion, peak[0] + exclusion + 1) % rows
    col_index = np.arange(peak[1] - exclusion, peak[1] + exclusion + 1) % cols
    box = surface[np.ix_(row_index, col_index)].astype(np.float64)
    count = surface.size - box.size
    total = float(surface.sum(dtype=np.float64)) - box.sum()
    squares = float(np.vdot(surface, surface).real) - float((box * box).sum())
    mean = total / count
    variance = max(squares / count - mean * mean, 1e-30)
    return (float(surface[peak]) - mean) / np.sqrt(variance)


def confidence_from_psr(psr: float) -> float:
    """Map a peak-to-sidelobe ratio to [0, 1] (see the module docstring)."""
    return float(1.0 - np.exp(-max(psr - 6.0, 0.0) / 8.0))


@dataclass(frozen=True)
class PhasePlaneBand:
    """The part of the half-plane spectrum the sub-pixel fit uses: frequencies up to
    ``band`` cycles/pixel (a disc), held as the two row blocks of the rectangle that
    contains it, so no gathering is needed per frame."""

    row_count: int
    col_count: int
    frequency_rows: np.ndarray  # (rows in band, 1), cycles/pixel
    frequency_cols: np.ndarray  # (1, cols in band)
    weights: np.ndarray  # disc mask (and prefilter, when filtered) on the rectangle

    @classmethod
    def for_shape(cls, shape: tuple[int, int], band: float, extra_weight: np.ndarray | None = None) -> "PhasePlaneBand":
        rows, cols = shape
        row_count = min(int(np.floor(band * rows)) + 1, rows // 2)
        col_count = min(int(np.floor(band * cols)) + 1, cols // 2 + 1)
        v = np.concatenate([np.arange(row_count), np.arange(rows - row_count + 1, rows)])
        v = np.where(v < rows / 2, v, v - rows) / rows
        u = np.arange(col_count) / cols
        radius = np.hypot(v[:, None], u[None, :])
        weights = ((radius > 0) & (radius <= band)).astype(np.float32)
        if extra_weight is not None:
            weights *= cls._take(extra_weight, row_count, col_count)
        return cls(row_count, col_count, v[:, None].astype(np.float32), u[None, :].astype(np.float32), weights)

    @staticmethod
    def _take(spectrum: np.ndarray, row_count: int, col_count: int) -> np.ndarray:
        return np.concatenate([spectrum[:row_count, :col_count], spectrum[-(row_count - 1):, :col_count]])

    def take(self, spectrum: np.ndarray) -> np.ndarray:
        return self._take(spectrum, self.row_count, self.col_count)


def refine_by_phase_plane(cross: np.ndarray, band: PhasePlaneBand, shift: tuple[float, float],
                          iterations: int = 8) -> tuple[float, float]:
    """Refine a shift by a weighted least-squares fit of the cross-power phase plane.

    The phase of the cross-power spectrum G conj(F) is -2 pi (u dx + v dy) (eq. 18).
    After removing the current estimate the residual phase phi is small, and the
    magnitude-weighted fit of a plane through it gives the residual shift in closed
    form. This is the paper's "first way" of solving eq. 18, used as a refinement of
    the peak (eq. 20-22): unbiased by the peak's shape and cheaper than an upsampled DFT.
    Gauss-Newton on sin(phi) = Im(Psi e^{i 2 pi (u dx + v dy)}) avoids an arctangent;
    its fixed point is the same, and it down-weights phase outliers.
    """
    dy, dx = shift
    weighted = band.take(cross) * band.weights  # weights * |cross| * Psi
    magnitude = np.abs(weighted)
    u, v = band.frequency_cols[0], band.frequency_rows[:, 0]
    column_sums = magnitude.sum(axis=0)
    suu = float(column_sums @ (u * u))
    svv = float(magnitude.sum(axis=1) @ (v * v))
    suv = float(v @ magnitude @ u)
    determinant = suu * svv - suv * suv
    if determinant <= 0:
        return dy, dx
    for _ in range(iterations):
        # The ramp e^{i 2 pi (u dx + v dy)} is separable, so the residual's weighted
        # sums sum_{v,u} u Im(W a(v) b(u)) and sum v Im(W a b) are two small
        # matrix-vector products rather than a pass over the band.
        a = np.exp(2j * np.pi * v * dy).astype(np.complex64)
        b = np.exp(2j * np.pi * u * dx).astype(np.complex64)
        projected = np.stack([a, v * a]) @ weighted  # (2, cols)
        bu = -float((projected[0] @ (u * b)).imag) / (2 * np.pi)
        bv = -float((projected[1] @ b).imag) / (2 * np.pi)
        ddx = (svv * bu - suv * bv) / determinant
        ddy = (suu * bv - suv * bu) / determinant
        dx, dy = dx + ddx, dy + ddy
        if abs(ddx) < 1e-3 and abs(ddy) < 1e-3:  # a thousandth of a pixel is plenty
            break
    return dy, dx


# --------------------------------------------------------------------------------------
# Rotation (section II-B-1)


def highpass_emphasis(shape: tuple[int, int]) -> np.ndarray:
    """Reddy & Chatterji's high-pass H = (1 - X)(2 - X), X = cos(pi u) cos(pi v), on the
    real-input half plane: it damps the low frequencies that the window and the DC
    dominate, so the log-polar correlation follows the image's structure."""
    rows, cols = shape
    v = np.fft.fftfreq(rows)[:, None]
    u = np.fft.rfftfreq(cols)[None, :]
    x = np.cos(np.pi * u) * np.cos(np.pi * v)
    return ((1 - x) * (2 - x)).astype(np.float32)


@dataclass(frozen=True)
class LogPolarGrid:
    """Where to sample a half-plane spectrum on a log-polar grid (eq. 11).

    Angles span 180 degrees (the magnitude spectrum of a real image is centrally
    symmetric, so that is a full period) from -90 to +90 degrees, i.e. u >= 0 only, which
    the real-input half plane holds. Radii are log-spaced in cycles per pixel, so a
    non-square image is sampled in physical frequency, not in bins. The lowest radii
    are left out: there the window's leakage outweighs the scene.
    """

    map_cols: np.ndarray
    map_rows: np.ndarray
    angles: int

    @classmethod
    def for_shape(cls, shape: tuple[int, int], angles: int = 720, radii: int = 96,
                  min_radius: float = 0.02, max_radius: float = 0.45) -> "LogPolarGrid":
        rows, cols = shape
        theta = np.deg2rad(-90 + 180 * np.arange(angles) / angles)
        rho = np.geomspace(min_radius, max_radius, radii)
        u = rho[:, None] * np.cos(theta)[None, :]
        v = rho[:, None] * np.sin(theta)[None, :]
        # Spectrum rows are fft-shifted so v = 0 sits at row rows // 2.
        return cls(
            map_cols=(u * cols).astype(np.float32),
            map_rows=(v * rows + rows // 2).astype(np.float32),
            angles=angles,
        )


def log_polar_magnitude(spectrum: np.ndarray, emphasis: np.ndarray, grid: LogPolarGrid) -> np.ndarray:
    """Emphasized log-magnitude spectrum resampled on ``grid`` (radii x angles)."""
    magnitude = np.log1p(np.abs(spectrum) * emphasis)
    shifted = np.fft.fftshift(magnitude, axes=0)
    return cv2.remap(shifted, grid.map_cols, grid.map_rows, interpolation=cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


def angular_spectrum(log_polar: np.ndarray) -> np.ndarray:
    """FFT along the angle of each radius, mean removed: what eq. 12 correlates."""
    centred = log_polar - log_polar.mean(axis=1, keepdims=True)
    return np.fft.rfft(centred, axis=1)


@dataclass(frozen=True)
class AngularRefiner:
    """Evaluates a band-limited circular correlation on a fine grid of +-1 sample
    around its peak: a local upsampled inverse DFT, with the matrix built once."""

    angles: int
    offsets: np.ndarray
    fine_basis: np.ndarray  # (fine points, frequencies)
    hermitian_weights: np.ndarray

    @classmethod
    def for_angles(cls, angles: int, upsample: int = 100) -> "AngularRefiner":
        offsets = np.linspace(-1, 1, 2 * upsample + 1)
        k = np.arange(angles // 2 + 1)
        weights = np.full(k.size, 2.0)
        weights[0] = 1.0
        if angles % 2 == 0:
            weights[-1] = 1.0
        return cls(angles, offsets, np.exp(2j * np.pi * np.outer(offsets, k) / angles), weights)

    def peak(self, cross: np.ndarray) -> tuple[float, float]:
        """(sub-sample peak position in [-angles/2, angles/2), peak height) of the
        inverse transform of the normalized 1-D cross spectrum ``cross``."""
        surface = np.fft.irfft(cross, n=self.angles)
        coarse = int(np.argmax(surface))
        k = np.arange(cross.size)
        at_coarse = self.hermitian_weights * cross * np.exp(2j * np.pi * coarse * k / self.angles)
        fine = (self.fine_basis @ at_coarse).real
        best = coarse + float(self.offsets[int(np.argmax(fine))])
        return centred_shift(best % self.angles, self.angles), float(surface[coarse])


def angular_shift(current: np.ndarray, reference: np.ndarray, refiner: AngularRefiner) -> tuple[float, float]:
    """Circular shift (samples) of the current angular profile against the reference
    (eq. 12), from the normalized cross spectrum summed over radii; sub-sample by
    :class:`AngularRefiner`. Returns (shift, peak height)."""
    cross = (current * np.conj(reference)).sum(axis=0)
    cross /= np.maximum(np.abs(cross), 1e-30)
    return refiner.peak(cross)


def rotate_about_centre(image: np.ndarray, angle_deg: float) -> np.ndarray:
    """Rotate content counter-clockwise as displayed by ``angle_deg`` about
    ((cols - 1) / 2, (rows - 1) / 2), bilinear, borders reflected."""
    rows, cols = image.shape
    matrix = cv2.getRotationMatrix2D(((cols - 1) / 2, (rows - 1) / 2), angle_deg, 1.0)
    return cv2.warpAffine(image, matrix, (cols, rows), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


# --------------------------------------------------------------------------------------
# Mask references (paper case 6)


def polygon_mask(shape: tuple[int, int], corners: Sequence[Sequence[float]]) -> np.ndarray:
    """Boolean mask of ``shape`` that is True inside the polygon of (x, y) corners."""
    if len(corners) < 3:
        raise ValueError(f"a polygon needs at least 3 corner points, got {len(corners)}")
    points = [(float(x), float(y)) for x, y in corners]
    canvas = Image.new("1", (shape[1], shape[0]), 0)
    ImageDraw.Draw(canvas).polygon(points, fill=1, outline=1)
    return np.asarray(canvas, dtype=bool)


def mask_reference(reference: np.ndarray, mask) -> np.ndarray:
    """The two-level image that stands in for a taught reference (paper case 6).

    ``mask`` is a boolean array of the reference's shape or a list of (x, y) polygon
    corners. Inside and outside take the reference's mean grey levels there, so the
    mask has the scene's polarity (phase correlation needs it); its edges are softened
    by a 1-pixel Gaussian, like the probe blur of a real image.
    """
    if isinstance(mask, np.ndarray) and mask.ndim == 2:
        if mask.shape != reference.shape:
            raise ValueError(f"mask is {mask.shape}, reference is {reference.shape}")
        region = mask.astype(bool)
    else:
        region = polygon_mask(reference.shape, mask)
    if region.all() or not region.any():
        raise ValueError("the mask must cover part of the image, not none or all of it")
    inside = float(reference[region].mean())
    outside = float(reference[~region].mean())
    if inside == outside:
        inside, outside = 1.0, 0.0
    two_level = np.where(region, inside, outside).astype(np.float32)
    return cv2.GaussianBlur(two_level, (0, 0), 1.0)


# --------------------------------------------------------------------------------------
# FFT plans


def wisdom_path() -> Path:
    """Where FFTW wisdom is kept between runs (``SEMSERVO_FFTW_WISDOM`` overrides)."""
    default = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "semservo" / "fftw-wisdom.pickle"
    return Path(os.environ.get("SEMSERVO_FFTW_WISDOM", default))


_wisdom_lock = threading.Lock()
_wisdom_loaded = False


def _load_wisdom() -> None:
    global _wisdom_loaded
    with _wisdom_lock:
        if _wisdom_loaded:
            return
        _wisdom_loaded = True
        try:
            pyfftw.import_wisdom(pickle.loads(wisdom_path().read_bytes()))
        except (OSError, pickle.UnpicklingError, EOFError, ValueError, TypeError):
            pass  # no wisdom yet: plans are measured once and saved


def _save_wisdom() -> None:
    path = wisdom_path()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary = path.with_suffix(f".{os.getpid()}.tmp")
        temporary.write_bytes(pickle.dumps(pyfftw.export_wisdom()))
        temporary.replace(path)
    except OSError as error:
        log.debug("could not save FFTW wisdom to %s: %s", path, error)


@dataclass
class FFTPlans:
    """Real-input forward and inverse 2-D FFTs of one shape, planned once (FFTW)."""

    forward: pyfftw.FFTW
    inverse: pyfftw.FFTW

    @classmethod
    def for_shape(cls, shape: tuple[int, int], effort: str = "FFTW_MEASURE", threads: int = 1) -> "FFTPlans":
        _load_wisdom()
        before = pyfftw.export_wisdom()
        real = pyfftw.empty_aligned(shape, dtype="float32")
        spectrum = pyfftw.empty_aligned((shape[0], shape[1] // 2 + 1), dtype="complex64")
        plans = cls(
            forward=pyfftw.FFTW(real, spectrum, axes=(0, 1), direction="FFTW_FORWARD", flags=(effort,), threads=threads),
            inverse=pyfftw.FFTW(spectrum.copy(), real.copy(), axes=(0, 1), direction="FFTW_BACKWARD",
                                flags=(effort, "FFTW_DESTROY_INPUT"), threads=threads),
        )
        if pyfftw.export_wisdom() != before:
            _save_wisdom()
        return plans

    def rfft2(self, image: np.ndarray) -> np.ndarray:
        """Spectrum of ``image``; the returned array is the plan's buffer, reused next call."""
        self.forward.input_array[...] = image
        return self.forward()

    def irfft2(self, spectrum: np.ndarray) -> np.ndarray:
        """Real inverse (normalized); the returned array is the plan's buffer."""
        self.inverse.input_array[...] = spectrum
        return self.inverse(normalise_idft=True)


# --------------------------------------------------------------------------------------
# The estimator


class MotionEstimator:
    """Measures rotation and sub-pixel translation of images against one reference.

    Parameters
    ----------
    reference : 2-D array (8/16-bit integers or float), at least 64 x 64.
    rotation : estimate rotation about the beam (section II-B-1) before translation.
    mask : boolean array or (x, y) polygon corners; the reference becomes the two-level
        mask image (paper case 6), see :func:`mask_reference`. The mask defines the target
        position: the estimate is the motion that brings the object onto the mask. Only
        the mask's outline carries information, so the correlation is band-limited to
        low frequencies (Gaussian, ``mask_band`` cycles/pixel) and rotation is not
        estimated (``rotation_deg`` is 0). A mask cannot tell apart repeated copies of a
        similar shape in the field (the paper's observed limitation): the strongest
        match wins, and ``confidence`` drops when several match equally.
    window : apodization, see :func:`apodization_window`.
    snr_threshold_db : frames whose SNR is below this are filtered (section II-D).
    band : the highest spatial frequency (cycles/pixel) the sub-pixel fit uses.
    fft_effort : FFTW planner effort; plans are made once here and kept as wisdom.

    An estimator is not thread-safe (its FFT buffers are reused); use one per thread.
    """

    min_confidence = 0.5

    def __init__(
        self,
        reference,
        *,
        rotation: bool = True,
        mask=None,
        window: str = "tukey",
        snr_threshold_db: float = DEFAULT_SNR_THRESHOLD_DB,
        band: float = 0.35,
        fft_effort: str = "FFTW_MEASURE",
        angles: int = 720,
        mask_band: float = 0.05,
    ):
        reference = as_image(reference, "reference")
        if mask is not None:
            reference = mask_reference(reference, mask)
            rotation = False
        self.shape = reference.shape
        self.rotation = rotation
        self.snr_threshold_db = snr_threshold_db
        self.window = apodization_window(self.shape, window)
        self.plans = FFTPlans.for_shape(self.shape, fft_effort)
        self.prefilter = gaussian_transfer(self.shape)
        self.lowpass = gaussian_lowpass(self.shape, mask_band) if mask is not None else None
        self.fit_band = PhasePlaneBand.for_shape(self.shape, band, extra_weight=self.lowpass)
        filtered_weight = self.prefilter if self.lowpass is None else self.prefilter * self.lowpass
        self.filtered_fit_band = PhasePlaneBand.for_shape(self.shape, band, extra_weight=filtered_weight)

        self.reference_snr_db = estimate_snr_db(reference)
        self.reference_conjugate = np.conj(self._spectrum(reference, self.window))
        # The whole-pixel search and the rotation run on a 2x block-averaged pair
        # (four times cheaper FFTs, and averaging lifts the SNR); full resolution is
        # needed only for the sub-pixel fit, which needs no inverse FFT.
        self.search_factor = 2 if min(self.shape) >= 2 * MIN_SIZE else 1
        search_reference = block_mean(reference, self.search_factor)
        self.search_shape = search_reference.shape
        self.search_window = apodization_window(self.search_shape, window)
        self.search_plans = FFTPlans.for_shape(self.search_shape, fft_effort)
        search_spectrum = self._search_spectrum(search_reference)
        self.search_reference_conjugate = np.conj(search_spectrum)
        self.search_lowpass = (
            gaussian_lowpass(self.search_shape, mask_band * self.search_factor) if mask is not None else None
        )

        if rotation:
            # Rotation reads the full-resolution spectrum: block averaging folds fine
            # structure back (aliasing), and folded energy does not turn with the
            # scene, which pulls small angles towards zero.
            self.grid = LogPolarGrid.for_shape(self.shape, angles=angles)
            self.refiner = AngularRefiner.for_angles(angles)
            self.emphasis = highpass_emphasis(self.shape)
            self.reference_angular = angular_spectrum(
                log_polar_magnitude(np.conj(self.reference_conjugate), self.emphasis, self.grid)
            )
            # Half the search resolution settles the 180-degree ambiguity cheaply.
            coarse = block_mean(search_reference, 2)
            self.coarse_window = apodization_window(coarse.shape, window)
            self.coarse_reference_conjugate = np.conj(np.fft.rfft2(self.coarse_window * (coarse - coarse.mean())))

    # -- helpers ----------------------------------------------------------------
    def _spectrum(self, image: np.ndarray, window: np.ndarray) -> np.ndarray:
        """FFT of the mean-free, apodized image, written straight into the plan's input."""
        buffer = self.plans.forward.input_array
        np.subtract(image, np.float32(image.mean(dtype=np.float64)), out=buffer)
        buffer *= window
        return self.plans.forward()

    def _search_spectrum(self, search: np.ndarray) -> np.ndarray:
        """FFT of the mean-free, apodized search image; a copy (the plan's buffer is reused)."""
        buffer = self.search_plans.forward.input_array
        np.subtract(search, np.float32(search.mean(dtype=np.float64)), out=buffer)
        buffer *= self.search_window
        return self.search_plans.forward().copy()

    def _check(self, image) -> np.ndarray:
        image = as_image(image)
        if image.shape != self.shape:
            raise ValueError(f"image is {image.shape[1]} x {image.shape[0]}, the reference is "
                             f"{self.shape[1]} x {self.shape[0]}")
        return image

    # -- steps ------------------------------------------------------------------
    def estimate_rotation(self, image: np.ndarray, search: np.ndarray) -> float:
        """Rotation of the content (degrees, counter-clockwise as displayed), in (-180, 180],
        of the full-resolution ``image`` (``search`` is its 2x block mean).

        Eq. 9-12: the log-polar magnitude spectra differ by a shift along the angle. The
        magnitude cannot tell theta from theta + 180 (it is centrally symmetric), so both
        are tried: the image de-rotated by theta and its 180-degree turn are correlated
        with the reference at half the search resolution, and the stronger peak wins.
        For a real image under a symmetric window the turned image's spectrum is the
        conjugate (up to a one-pixel shift), so one coarse FFT serves both candidates.
        """
        spectrum = self._spectrum(image, self.window)
        current = angular_spectrum(log_polar_magnitude(spectrum, self.emphasis, self.grid))
        samples, _ = angular_shift(current, self.reference_angular, self.refiner)
        # Angles run from -90 (column 0 of the log-polar grid) to +90 degrees with v
        # along rows (down), so a counter-clockwise turn as displayed moves the profile back.
        angle = -samples * 180.0 / self.grid.angles
        coarse = block_mean(rotate_about_centre(search, -angle), 2)
        coarse_spectrum = np.fft.rfft2(self.coarse_window * (coarse - coarse.mean()))
        heights = []
        for candidate in (coarse_spectrum, np.conj(coarse_spectrum)):
            normalized, _ = normalized_cross_power(candidate, self.coarse_reference_conjugate)
            heights.append(float(np.fft.irfft2(normalized, s=coarse.shape).max()))
        if heights[1] > heights[0]:
            angle += 180.0 if angle <= 0 else -180.0
        return float(angle)

    def estimate_translation(self, image: np.ndarray, search_spectrum: np.ndarray, *,
                             filtered: bool) -> tuple[float, float, float, float]:
        """(dx, dy, peak height, PSR) of ``image`` against the reference.

        1. Search: the peak of the inverse normalized cross-power spectrum (eq. 18-20)
           of the 2x block-averaged pair (``search_spectrum`` is the current one's),
           sub-pixel by Foroosh's neighbour ratio (eq. 21-22), centred (eq. 23-24). Its
           sharpness gives the confidence.
        2. The full-resolution image is windowed with the window moved by the nearest
           whole-pixel shift (:func:`shifted_window`), so both images weight the same
           scene: a window fixed on the frame biases the estimate towards zero.
        3. The residual sub-pixel shift is fitted on the full-resolution phase plane
           (:func:`refine_by_phase_plane`); when the frame is filtered (section II-D)
           the fit is weighted by the 5 x 5 Gaussian's transfer function.
        """
        factor = self.search_factor
        cross = search_spectrum * self.search_reference_conjugate
        # Psi = cross / |cross| (eq. 18), as a real multiply on the interleaved
        # (re, im) floats: several times faster than numpy's complex-by-real divide.
        scale = np.abs(cross)
        np.maximum(scale, np.finfo(np.float32).tiny, out=scale)
        np.reciprocal(scale, out=scale)
        if self.search_lowpass is not None:
            scale *= self.search_lowpass
        normalized = self.search_plans.inverse.input_array
        np.multiply(_pairs(cross), scale[..., None], out=_pairs(normalized))
        surface = self.search_plans.inverse(normalise_idft=True)
        peak = np.unravel_index(int(np.argmax(surface)), surface.shape)
        psr = peak_to_sidelobe(surface, peak)
        height = float(surface[peak])
        offset_row, offset_col = foroosh_subpixel(surface, peak)
        dy = (centred_shift(peak[0], self.search_shape[0]) + offset_row) * factor
        dx = (centred_shift(peak[1], self.search_shape[1]) + offset_col) * factor
        window = shifted_window(self.window, int(round(dy)), int(round(dx)))
        cross = self._spectrum(image, window) * self.reference_conjugate
        band = self.filtered_fit_band if filtered else self.fit_band
        dy, dx = refine_by_phase_plane(cross, band, (dy, dx))
        return dx, dy, height, psr

    def estimate(self, image) -> Motion:
        """Motion of ``image`` against the reference. ValueError for bad input."""
        image = self._check(image)
        snr_db = estimate_snr_db(image)
        filtered = snr_db < self.snr_threshold_db or self.reference_snr_db < self.snr_threshold_db
        search = block_mean(image, self.search_factor)
        search_spectrum = self._search_spectrum(search)
        angle = 0.0
        if self.rotation:
            angle = self.estimate_rotation(image, search)
            if abs(angle) > 1e-3:
                # Rotation first, as the paper says: translation is measured on the
                # de-rotated image.
                image = rotate_about_centre(image, -angle)
                search_spectrum = self._search_spectrum(block_mean(image, self.search_factor))
            else:
                angle = 0.0
        dx, dy, height, psr = self.estimate_translation(image, search_spectrum, filtered=filtered)
        if angle:
            # The shift was measured on the de-rotated image; turn it back into the
            # current image's axes (counter-clockwise as displayed, rows down).
            theta = np.deg2rad(angle)
            dx, dy = dx * np.cos(theta) + dy * np.sin(theta), -dx * np.sin(theta) + dy * np.cos(theta)
        return Motion(
            dx=float(dx), dy=float(dy), rotation_deg=float(angle),
            confidence=confidence_from_psr(psr), snr_db=float(snr_db),
            peak=height, psr=float(psr), filtered=bool(filtered),
        )
