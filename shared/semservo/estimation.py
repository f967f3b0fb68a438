"""Fourier-domain motion estimation between a taught reference and the current SEM image.

Implements section II-A to II-D of Marturi et al., "Image-Guided Nanopositioning Scheme
for SEM": rotation about the beam from the log-polar magnitude spectrum (eq. 9-12),
refined on the image itself, then sub-pixel translation from the normalized cross-power
spectrum (eq. 18-24), with the image SNR monitored (section II-D) and, on request, noisy
frames filtered.

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
With rotation, ``confidence`` is also never above ``rotation_confidence``: how clearly
the image's correlation peaks in the angle (:meth:`MotionEstimator.refine_rotation`), so
a scene whose turns all look alike has its estimate refused rather than guessed.
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

from semservo import _kernels

log = logging.getLogger(__name__)

MIN_SIZE = 64
#: Sidelobe exclusion half-width for the peak-to-sidelobe ratio (an 11 x 11 box).
PSR_EXCLUSION = 5
#: Below this SNR (dB) a frame is filtered with the 5 x 5 Gaussian (section II-D); None:
#: never. The paper's 15 dB is available (``snr_threshold_db=15``) but is not the
#: default: the magnitude-weighted fit already gives noisy frequencies little weight,
#: and the fixed Gaussian also removes the mid frequencies that carry a sparse scene's
#: edges (held-out images: 0.022 -> 0.036 px on a hole at low magnification, 0.024 ->
#: 0.032 px on the drift image; it gains 0.001-0.002 px on the 2013 frames).
DEFAULT_SNR_THRESHOLD_DB: float | None = None
#: Turns smaller than this are not undone before measuring translation (they are still
#: reported): a rotation about the image centre adds no net shift, and undoing a turn
#: at the rotation estimate's noise floor (0.02-0.03 degree on real frames) costs a
#: resampling (0.4 ms) and adds interpolation. Larger turns are undone: on real frames,
#: skipping a 0.1 degree turn moves the shift by up to 0.06 px, a 0.05 degree turn by
#: about 0.02 px.
DEROTATE_ABOVE_DEG = 0.05
#: Small turns are measured against copies of the reference turned by these angles
#: (degrees), see :meth:`MotionEstimator.estimate_rotation`.
TURNED_REFERENCE_DEG = (1.5, -1.5, 3.0, -3.0)
#: How many moved windows (or reference spectra under them), one per whole-pixel shift,
#: an estimator keeps: a servo loop sees few shifts.
MOVED_WINDOWS_KEPT = 64
#: The angle from the log-polar spectrum is refined by probe turns that move the edge of
#: the image's inscribed circle by this many pixels either way (see
#: :meth:`MotionEstimator.refine_rotation`): about where the correlation has fallen by
#: a measurable amount without leaving its parabolic top.
ROTATION_PROBE_PX = 1.0
#: Turns up to this many probes are refined without turning the frame back: it is fitted
#: straight against reference copies turned by whole probes. Turning the frame back by a
#: small angle with OpenCV's bicubic (or bilinear) kernel turns it by a slightly
#: different angle (the kernel's phase error at small sub-pixel moves: 0.3 degree turned
#: back acted as 0.34), which no probe could correct.
SMALL_TURN_PROBES = 3
#: How many peaks of the log-polar correlation are tried, highest first, when the image
#: shows no correlation top near the highest (see ``_estimate_with_rotation``).
ANGLE_CANDIDATES = 4
#: Bicubic for the turned images the angle is refined on: bilinear interpolation blurs
#: by an amount that depends on the turn (none at 0 and 90 degrees), which pulled the
#: refined angle towards those (0.05 degree mean error on a sparse scene, 0.008 bicubic).
PROBE_INTERPOLATION = cv2.INTER_CUBIC

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
    #: How well the image itself pins the angle down (1 when rotation is not measured);
    #: ``confidence`` is never above it. See :func:`confidence_from_sharpness`.
    rotation_confidence: float = 1.0

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
            "rotation_confidence": self.rotation_confidence,
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
    R(0) - R_s(0). The central half of the rows is used when the image is tall enough:
    plenty of pixels for the statistics at half the cost.
    """
    image = np.ascontiguousarray(image, dtype=np.float32)
    return _snr_from(_statistics(image))


def _statistics(image: np.ndarray) -> tuple:
    rows = image.shape[0]
    first, last = (rows // 4, rows - rows // 4) if rows >= 4 * MIN_SIZE else (0, rows)
    return _kernels.frame_statistics(image, first, last)


def _snr_from(statistics: tuple) -> float:
    _, _, zero_lag, down1, down2, along1, along2 = statistics
    if zero_lag <= 0:
        return float("-inf")
    signal = ((4 * down1 - down2) / 3 + (4 * along1 - along2) / 3) / 2
    signal = min(max(signal, 1e-12 * zero_lag), zero_lag)
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


def centred_shift(index: float, length: int) -> float:
    """Wrap a peak index to a signed shift in [-length/2, length/2) (eq. 23-24)."""
    return index - length if index >= length / 2 else index


def confidence_from_psr(psr: float) -> float:
    """Map a peak-to-sidelobe ratio to [0, 1] (see the module docstring)."""
    return float(1.0 - np.exp(-max(psr - 6.0, 0.0) / 8.0))


#: The rotation's sharpness (see :meth:`MotionEstimator.refine_rotation`) at which its
#: confidence is 1 - 1/e. Real SEM scenes lose 4e-4 to 2e-2 of their correlation when a
#: turn moves the image's edge by a pixel (six images of five instruments, at every
#: dose tried); a rotationally symmetric scene (a disc, a ring) loses under 3e-5, so
#: its angle is refused (confidence under 0.25) rather than guessed.
SHARPNESS_SCALE = 1e-4

def confidence_from_sharpness(sharpness: float) -> float:
    """Map the rotation's sharpness to [0, 1]: ``1 - exp(-sharpness / SHARPNESS_SCALE)``."""
    return float(1.0 - np.exp(-max(sharpness, 0.0) / SHARPNESS_SCALE))


@dataclass(frozen=True)
class PhasePlaneBand:
    """The part of the half-plane spectrum the sub-pixel fit uses: frequencies up to
    ``band`` cycles/pixel (a disc), as a list of spectrum rows times the first columns,
    with a weight per element (the disc, times any extra spectral weight)."""

    rows: np.ndarray  # spectrum row indices in the band
    frequency_rows: np.ndarray  # cycles/pixel of those rows
    frequency_cols: np.ndarray  # cycles/pixel of the first columns
    weights: np.ndarray  # (rows, cols)

    @classmethod
    def for_shape(cls, shape: tuple[int, int], band: float, extra_weight: np.ndarray | None = None) -> "PhasePlaneBand":
        rows, cols = shape
        row_count = min(int(np.floor(band * rows)) + 1, rows // 2)
        col_count = min(int(np.floor(band * cols)) + 1, cols // 2 + 1)
        indices = np.concatenate([np.arange(row_count), np.arange(rows - row_count + 1, rows)])
        v = np.where(indices < rows / 2, indices, indices - rows) / rows
        u = np.arange(col_count) / cols
        radius = np.hypot(v[:, None], u[None, :])
        weights = ((radius > 0) & (radius <= band)).astype(np.float64)
        if extra_weight is not None:
            weights *= extra_weight[indices][:, :col_count]
        return cls(indices.astype(np.int64), v.astype(np.float64), u.astype(np.float64), weights)


def crop_spectrum_into(spectrum: np.ndarray, out: np.ndarray) -> np.ndarray:
    """The lowest frequencies of a real-input half-plane ``spectrum``, as many as ``out``
    holds (rows split between the non-negative and the negative frequencies).

    With ``out`` shaped for an image of half the rows and columns, this is the spectrum
    of the image band-limited to half its Nyquist frequency and sampled at half the rate:
    an ideal (sinc) decimation, so the whole-pixel search runs on a quarter of the
    samples without a second forward FFT. Returns ``out``.
    """
    rows = out.shape[0]
    non_negative = (rows + 1) // 2
    negative = rows - non_negative
    cols = out.shape[1]
    out[:non_negative] = spectrum[:non_negative, :cols]
    if negative:
        out[non_negative:] = spectrum[spectrum.shape[0] - negative:, :cols]
    return out


def refine_on_band(current_spectrum: np.ndarray, reference_conjugate: np.ndarray, band: PhasePlaneBand,
                   shift: tuple[float, float], iterations: int = 8, tolerance: float = 1e-3,
                   workspace: np.ndarray | None = None, with_correlation: bool = False) -> tuple:
    """Sub-pixel shift (dy, dx) by Newton's method on the band-limited correlation surface.

    The cross-power spectrum C = G conj(F) has phase -2 pi (u dx + v dy) (eq. 18), so
    f(d) = Re sum_k w(k) C(k) e^{i 2 pi k.d} (the magnitude-weighted phase correlation
    of eq. 19, evaluated at a continuous shift d) peaks at the true shift. Starting
    from the peak of eq. 20-22, a few Newton steps on f's analytic gradient and Hessian
    find that maximum: the continuous equivalent of an upsampled DFT around the peak,
    at the cost of a few sums over the band and with no grid to quantize the result.
    This is also the paper's "first way" of solving eq. 18, the fit of the phase plane,
    weighted by the spectral magnitude.

    Returns (dy, dx), or (dy, dx, correlation) with ``with_correlation``: the
    normalized cross-correlation of the band-limited images at that shift (1 for a
    noise-free copy moved by a whole number of pixels).
    """
    if workspace is None:
        workspace = np.empty(band.weights.shape, np.complex128)
    dy, dx, _, correlation = _kernels.newton_on_band(
        current_spectrum, reference_conjugate, band.rows, band.frequency_rows, band.frequency_cols,
        band.weights, float(shift[0]), float(shift[1]), iterations, tolerance, workspace, with_correlation,
    )
    return (dy, dx, correlation) if with_correlation else (dy, dx)


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


def log_polar_magnitude(spectrum: np.ndarray, emphasis: np.ndarray, grid: LogPolarGrid,
                        workspace: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
    """Emphasized magnitude spectrum resampled on ``grid`` (radii x angles), then
    compressed by log(1 + x) (taken after resampling: half as many logarithms).

    ``workspace`` (spectrum-shaped float32) and ``out`` (radii x angles float32) may be
    given to avoid allocating on the per-frame path."""
    if workspace is None:
        workspace = np.empty(spectrum.shape, np.float32)
    _kernels.magnitude_shifted_into(spectrum, emphasis, workspace)
    resampled = cv2.remap(workspace, grid.map_cols, grid.map_rows, interpolation=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE, dst=out)
    # log(1 + x) as OpenCV's vectorized log of 1 + x: numpy's float32 log1p is scalar
    # code here (1.2 ms for 96 x 720 against 0.05 ms).
    resampled += 1.0
    return cv2.log(resampled, dst=resampled)


def angular_spectrum(log_polar: np.ndarray, plan: pyfftw.FFTW | None = None) -> np.ndarray:
    """FFT along the angle of each radius with the mean (DC) removed: what eq. 12
    correlates. ``plan`` is an FFTW plan for this shape (its buffer is returned)."""
    if plan is None:
        spectrum = np.fft.rfft(log_polar, axis=1)
    else:
        plan.input_array[...] = log_polar
        spectrum = plan()
    spectrum[:, 0] = 0
    return spectrum


@dataclass(frozen=True)
class AngularRefiner:
    """Evaluates a band-limited circular correlation near its peak by a local upsampled
    inverse DFT, in two stages (steps of 0.1, then 0.005 sample), bases built once."""

    angles: int
    coarse_offsets: np.ndarray
    coarse_basis: np.ndarray  # (points, frequencies)
    fine_offsets: np.ndarray
    fine_basis: np.ndarray
    hermitian_weights: np.ndarray
    frequencies: np.ndarray  # 0 .. angles // 2

    @classmethod
    def for_angles(cls, angles: int) -> "AngularRefiner":
        k = np.arange(angles // 2 + 1)
        weights = np.full(k.size, 2.0)
        weights[0] = 1.0
        if angles % 2 == 0:
            weights[-1] = 1.0
        coarse = np.linspace(-1, 1, 21)
        fine = np.linspace(-0.1, 0.1, 41)
        basis = lambda offsets: np.exp(2j * np.pi * np.outer(offsets, k) / angles).astype(np.complex64)  # noqa: E731
        return cls(angles, coarse, basis(coarse), fine, basis(fine), weights, k)

    def peak(self, cross: np.ndarray) -> tuple[float, float]:
        """(sub-sample peak position in [-angles/2, angles/2), peak height) of the
        inverse transform of the normalized 1-D cross spectrum ``cross``."""
        surface = np.fft.irfft(cross, n=self.angles)
        coarse = int(np.argmax(surface))
        k = self.frequencies
        weighted = (self.hermitian_weights * cross).astype(np.complex64)
        at_coarse = weighted * np.exp(2j * np.pi * coarse * k / self.angles).astype(np.complex64)
        first = float(self.coarse_offsets[int(np.argmax((self.coarse_basis @ at_coarse).real))])
        at_first = weighted * np.exp(2j * np.pi * (coarse + first) * k / self.angles).astype(np.complex64)
        second = float(self.fine_offsets[int(np.argmax((self.fine_basis @ at_first).real))])
        best = coarse + first + second
        return centred_shift(best % self.angles, self.angles), float(surface[coarse])


def angular_candidates(cross: np.ndarray, angles: int, count: int) -> list[int]:
    """The ``count`` highest local maxima (sample indices, centred) of the inverse
    transform of the 1-D cross spectrum ``cross``, highest first: where else the
    log-polar correlation says the angle may be."""
    surface = np.fft.irfft(cross, n=angles)
    is_peak = (surface >= np.roll(surface, 1)) & (surface > np.roll(surface, -1))
    peaks = np.flatnonzero(is_peak)
    order = peaks[np.argsort(surface[peaks])[::-1]][:count]
    return [int(centred_shift(int(index), angles)) for index in order]


def angular_shift(current: np.ndarray, reference_conjugate: np.ndarray, refiner: AngularRefiner) -> tuple[float, float]:
    """Circular shift (samples) of the current angular profile against the reference
    (eq. 12; ``reference_conjugate`` is its conjugated angular spectrum), from the
    normalized cross spectrum summed over radii; sub-sample by :class:`AngularRefiner`.
    Returns (shift, peak height)."""
    frequencies = current.shape[1]
    cross = np.empty(frequencies, np.complex64)
    _kernels.normalized_angular_cross_into(current, reference_conjugate[np.newaxis], np.ones((1, frequencies), np.complex64),
                                           np.empty(frequencies, np.complex64), cross)
    return refiner.peak(cross)


def rotate_about_centre(image: np.ndarray, angle_deg: float, out: np.ndarray | None = None,
                        interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """Rotate content counter-clockwise as displayed by ``angle_deg`` about
    ((cols - 1) / 2, (rows - 1) / 2), borders reflected; bilinear unless an OpenCV
    ``interpolation`` flag says otherwise."""
    rows, cols = image.shape
    matrix = cv2.getRotationMatrix2D(((cols - 1) / 2, (rows - 1) / 2), angle_deg, 1.0)
    return cv2.warpAffine(image, matrix, (cols, rows), dst=out, flags=interpolation,
                          borderMode=cv2.BORDER_REFLECT)


# --------------------------------------------------------------------------------------
# Mask references (paper case 6)


def _motion(shift: tuple[float, float], angle: float, derotated: bool, height: float, psr: float, snr_db: float,
            filtered: bool, rotation_confidence: float = 1.0) -> Motion:
    """The estimate, its shift (dy, dx) turned back into the current image's axes when
    it was measured on the de-rotated image (counter-clockwise as displayed, rows down)."""
    dy, dx = shift
    if derotated:
        theta = np.deg2rad(angle)
        dx, dy = dx * np.cos(theta) + dy * np.sin(theta), -dx * np.sin(theta) + dy * np.cos(theta)
    return Motion(dx=float(dx), dy=float(dy), rotation_deg=float(angle),
                  confidence=min(confidence_from_psr(psr), rotation_confidence), snr_db=float(snr_db), peak=height,
                  psr=float(psr), filtered=bool(filtered), rotation_confidence=float(rotation_confidence))


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
#: The wisdom files already read into this process (the setting may name another later).
_wisdom_loaded: set[Path] = set()


def _load_wisdom(path: Path) -> None:
    with _wisdom_lock:
        if path in _wisdom_loaded:
            return
        _wisdom_loaded.add(path)
        try:
            pyfftw.import_wisdom(pickle.loads(path.read_bytes()))
        except (OSError, pickle.UnpicklingError, EOFError, ValueError, TypeError):
            log.debug("no FFTW wisdom at %s yet: plans are measured once and saved", path)


def _save_wisdom(path: Path) -> None:
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
        path = wisdom_path()
        _load_wisdom(path)
        before = pyfftw.export_wisdom()
        real = pyfftw.empty_aligned(shape, dtype="float32")
        spectrum = pyfftw.empty_aligned((shape[0], shape[1] // 2 + 1), dtype="complex64")
        plans = cls(
            forward=pyfftw.FFTW(real, spectrum, axes=(0, 1), direction="FFTW_FORWARD", flags=(effort,), threads=threads),
            inverse=pyfftw.FFTW(spectrum.copy(), real.copy(), axes=(0, 1), direction="FFTW_BACKWARD",
                                flags=(effort, "FFTW_DESTROY_INPUT"), threads=threads),
        )
        # Saved when planning learned something, and also when this file lacks what the
        # process already knew (plans made earlier, under another wisdom path).
        if pyfftw.export_wisdom() != before or not path.is_file():
            _save_wisdom(path)
        return plans


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
    precision : ``"full"`` (default) fits the sub-pixel shift on the frame's
        full-resolution spectrum, from one forward FFT (the whole-pixel search reads the
        spectrum's low-frequency quarter; the reference under the moved window is
        computed once per whole-pixel shift). ``"fast"`` fits it on the half-resolution
        pair: about 0.75 x the time, and 1.5-3 x the error on smooth, low-texture scenes
        (a FIB-SEM slice: 0.037 against 0.012 px). ``bench/sem_images.py`` measures both.
    rotation_confidence : every Motion carries how well the image pins the angle down
        (:meth:`refine_rotation`); a scene whose turns all look alike is refused.

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
        snr_threshold_db: float | None = DEFAULT_SNR_THRESHOLD_DB,
        band: float = 0.35,
        fft_effort: str = "FFTW_MEASURE",
        angles: int = 720,
        mask_band: float = 0.05,
        precision: str = "full",
    ):
        if precision not in ("full", "fast"):
            raise ValueError(f"precision must be 'full' or 'fast', not {precision!r}")
        self.precision = precision
        self.fft_effort = fft_effort
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
        self.no_weight = np.ones((1, 1), np.float32)
        filtered_weight = self.prefilter if self.lowpass is None else self.prefilter * self.lowpass
        self.filtered_fit_band = PhasePlaneBand.for_shape(self.shape, band, extra_weight=filtered_weight)

        self.reference_snr_db = estimate_snr_db(reference)
        self.reference_conjugate = np.conj(self._spectrum(reference, float(reference.mean())))
        # The whole-pixel search runs on a pair halved by a binomial filter (four times
        # cheaper FFTs, and the filter lifts the SNR); full resolution is needed only
        # for the sub-pixel fit (precision="full"), which needs no inverse FFT.
        self.search_factor = 2 if min(self.shape) >= 2 * MIN_SIZE else 1
        self.search_shape = (self.shape[0] // self.search_factor, self.shape[1] // self.search_factor)
        self._search_scratch = np.empty((self.shape[0], self.search_shape[1]), np.float32)
        self._search_block = np.empty(self.search_shape, np.float32)
        search_reference = self._halve(reference)
        self.search_window = apodization_window(self.search_shape, window)
        self.search_plans = FFTPlans.for_shape(self.search_shape, fft_effort)
        search_spectrum = self._search_spectrum(search_reference, float(search_reference.mean()))
        self.search_reference_conjugate = np.conj(search_spectrum)
        self.search_lowpass = (
            gaussian_lowpass(self.search_shape, mask_band * self.search_factor) if mask is not None else None
        )
        # The fast fit's reference: the full-resolution window applied before halving.
        _kernels.apodize_halve_into(reference, float(reference.mean()), self.window, 0, 0, self._search_scratch,
                                    self.search_plans.forward.input_array)
        self.fit_search_reference_conjugate = np.conj(self.search_plans.forward())
        # The fit band is in cycles per pixel of the image it applies to; the mask's
        # low-pass and the prefilter are physical, so they scale with the search factor.
        search_lowpass = gaussian_lowpass(self.search_shape, mask_band * self.search_factor) if mask is not None else 1
        self.search_fit_band = PhasePlaneBand.for_shape(
            self.search_shape, band, extra_weight=None if mask is None else search_lowpass)
        self.search_filtered_fit_band = PhasePlaneBand.for_shape(
            self.search_shape, band,
            extra_weight=gaussian_transfer(self.search_shape, sigma=1.0 / self.search_factor) * search_lowpass)
        # The full-precision path searches on the low-frequency quarter of the frame's own
        # full-resolution spectrum (see crop_spectrum_into) and fits against the
        # reference under a window moved by the whole-pixel shift, computed once per
        # shift with plans of its own (the frame's spectrum stays in its buffer).
        self.cropped_reference_conjugate = np.empty_like(self.search_reference_conjugate)
        crop_spectrum_into(self.reference_conjugate, self.cropped_reference_conjugate)
        self._cropped = np.empty_like(self.search_reference_conjugate)
        quarter_shape = (self.search_shape[0] // 2, self.search_shape[1] // 2)
        self.quarter_plans = FFTPlans.for_shape(quarter_shape, fft_effort)
        self._quarter_spectrum = np.empty((quarter_shape[0], quarter_shape[1] // 2 + 1), np.complex64)
        self._quarter_reference = np.empty_like(self._quarter_spectrum)
        self._reference = reference
        self._reference_mean = float(reference.mean())
        self._reference_plans: FFTPlans | None = None
        self._moved_references: dict[tuple[int, int], np.ndarray] = {}
        # Per-frame buffers, allocated once: large temporaries cost page faults.
        self._search_band_workspace = np.empty(self.search_fit_band.weights.shape, np.complex128)
        self._search_block = np.empty(self.search_shape, np.float32)
        self._band_workspace = np.empty(self.fit_band.weights.shape, np.complex128)

        if rotation:
            # Rotation reads the full-resolution spectrum: block averaging folds fine
            # structure back (aliasing), and folded energy does not turn with the
            # scene, which pulls small angles towards zero.
            self.grid = LogPolarGrid.for_shape(self.shape, angles=angles)
            self.refiner = AngularRefiner.for_angles(angles)
            self.emphasis = highpass_emphasis(self.shape)
            self.reference_angular_conjugate = np.conj(angular_spectrum(
                log_polar_magnitude(np.conj(self.reference_conjugate), self.emphasis, self.grid)
            )).astype(np.complex64)
            # Copies of the reference turned by a known angle, for small turns (see
            # estimate_rotation); Lanczos, since it is done once.
            turned_conjugates = []
            for turn in TURNED_REFERENCE_DEG:
                turned = rotate_about_centre(reference, turn, interpolation=cv2.INTER_LANCZOS4)
                spectrum = self._spectrum(turned, float(turned.mean()))
                turned_conjugates.append(np.conj(angular_spectrum(log_polar_magnitude(spectrum, self.emphasis, self.grid))))
            self.turned_reference_angular_conjugates = np.stack(turned_conjugates).astype(np.complex64)
            # Each turned comparison peaks at (turn - 0) samples off; these ramps move
            # every peak back onto the true turn, so the four add into one surface.
            frequencies = np.arange(angles // 2 + 1)
            turn_samples = np.asarray(TURNED_REFERENCE_DEG) * angles / 180.0
            self.turned_reference_ramps = np.exp(
                2j * np.pi * np.outer(turn_samples, frequencies) / angles).astype(np.complex64)
            self.turned_reference_below_deg = min(map(abs, TURNED_REFERENCE_DEG)) / 2
            self.angular_plan = pyfftw.FFTW(
                pyfftw.empty_aligned(self.grid.map_cols.shape, "float32"),
                pyfftw.empty_aligned((self.grid.map_cols.shape[0], angles // 2 + 1), "complex64"),
                axes=(1,), flags=(fft_effort,),
            )
            self._unit_ramp = np.ones((1, angles // 2 + 1), np.complex64)
            self._angular_accumulator = np.empty(angles // 2 + 1, np.complex64)
            self._angular_cross = np.empty(angles // 2 + 1, np.complex64)
            self._first_angular_cross = np.empty(angles // 2 + 1, np.complex64)
            self._log_magnitude = np.empty(self.reference_conjugate.shape, np.float32)
            self._log_polar = np.empty(self.grid.map_cols.shape, np.float32)
            self._derotated = np.empty(self.shape, np.float32)
            # The angle is refined on the halved pair (see refine_rotation), by probe turns
            # that move the inscribed circle's edge by ROTATION_PROBE_PX pixels.
            self.rotation_probe_deg = float(np.degrees(ROTATION_PROBE_PX / (min(self.shape) / 2)))
            self._half_image = np.empty(self.search_shape, np.float32)
            self._half_derotated = np.empty(self.search_shape, np.float32)
            self._half_derotated_by: float | None = None  # the turn self._half_derotated holds
            # The probes turn the reference, not the frame: the frame is fitted against
            # copies of the reference turned by whole probes, their spectra made once
            # (the halved pair under the full-resolution window, as the fast fit's).
            self.probe_reference_conjugates = {0: self.fit_search_reference_conjugate}
            if self.search_factor == 2:
                for probe in range(-SMALL_TURN_PROBES - 1, SMALL_TURN_PROBES + 2):
                    if probe == 0:
                        continue
                    turned = rotate_about_centre(reference, probe * self.rotation_probe_deg,
                                                 interpolation=cv2.INTER_LANCZOS4)
                    _kernels.apodize_halve_into(turned, float(reference.mean()), self.window, 0, 0,
                                                self._search_scratch, self.search_plans.forward.input_array)
                    self.probe_reference_conjugates[probe] = np.conj(self.search_plans.forward())
            self._unit_image = np.ones(self.shape, np.float32)
            self._moved_windows: dict[tuple[int, int], np.ndarray] = {}

    # -- helpers ----------------------------------------------------------------
    def _spectrum(self, image: np.ndarray, mean: float, row_shift: int = 0, col_shift: int = 0) -> np.ndarray:
        """FFT of the mean-free image under the window moved by (row_shift, col_shift),
        written straight into the plan's input; the result is the plan's buffer."""
        _kernels.apodize_into(image, mean, self.window, row_shift, col_shift, self.plans.forward.input_array)
        return self.plans.forward()

    def _search_spectrum(self, search: np.ndarray, mean: float) -> np.ndarray:
        """FFT of the mean-free, apodized search image; the plan's buffer."""
        _kernels.apodize_into(search, mean, self.search_window, 0, 0, self.search_plans.forward.input_array)
        return self.search_plans.forward()

    def _halve(self, image: np.ndarray) -> np.ndarray:
        """The search image of ``image`` (a copy in a new array; used once per reference)."""
        if self.search_factor == 1:
            return np.array(image, dtype=np.float32)
        halved = np.empty(self.search_shape, np.float32)
        _kernels.decimate_apodize_into(np.ascontiguousarray(image, dtype=np.float32), 0.0,
                                       np.ones(self.search_shape, np.float32), self._search_scratch, halved,
                                       np.empty(self.search_shape, np.float32))
        return halved

    def _search_spectrum_of(self, image: np.ndarray, mean: float) -> np.ndarray:
        """Halve ``image`` into ``self._search_block`` and return the FFT of its mean-free,
        apodized version (the plan's buffer), in one fused pass."""
        if self.search_factor == 1:
            self._search_block[...] = image
            return self._search_spectrum(self._search_block, mean)
        _kernels.decimate_apodize_into(image, mean, self.search_window, self._search_scratch,
                                       self._search_block, self.search_plans.forward.input_array)
        return self.search_plans.forward()

    def _check(self, image) -> tuple[np.ndarray, tuple]:
        """The image as contiguous float32 (no copy when it already is) and its statistics."""
        array = np.asarray(image)
        if array.ndim != 2 or array.size == 0 or array.dtype.kind not in "uifb":
            array = as_image(array)  # raises the precise ValueError
        if array.shape != self.shape:
            raise ValueError(f"image is {array.shape[1]} x {array.shape[0]}, the reference is "
                             f"{self.shape[1]} x {self.shape[0]}")
        array = np.ascontiguousarray(array, dtype=np.float32)
        statistics = _statistics(array)
        if not statistics[1]:
            raise ValueError("image contains NaN or infinite values")
        return array, statistics

    # -- steps ------------------------------------------------------------------
    def estimate_rotation(self, image: np.ndarray, mean: float) -> float:
        """Rotation of the content modulo 180 degrees (counter-clockwise as displayed), in
        [-90, 90): eq. 9-12, the log-polar magnitude spectra differ by a shift along the
        angle. The magnitude spectrum is centrally symmetric, so theta and theta + 180
        look alike; :meth:`estimate` settles which (see there).

        Small turns: the DFT samples the magnitude spectrum at the image's own Nyquist
        rate, but a magnitude (like the autocorrelation behind it) has twice the
        bandwidth, so the log-polar resampling between bins is aliased and a displacement
        under one bin reads biased towards zero, like pixel locking in particle image
        velocimetry. Below about 0.3 degree every radius moves less than a bin and the
        whole estimate locks near zero (0.1 degree read 0.007 on exactly rotated
        synthetic images). So a turn under 0.75 degree is measured again against copies
        of the reference turned by +-1.5 and +-3 degrees (``TURNED_REFERENCE_DEG``),
        made once: there each radius moves by a different fraction of a bin, the bias
        averages out over radii, and the mean over opposite offsets cancels what is left
        to first order. The image's log-polar spectrum is shared, so this costs one more
        1-D correlation against the four turned copies at once. Measured over turns from
        -0.8 to 0.6 degree: mean error 0.054 -> 0.004 degree on exact synthetic rotations
        (400 x 400), 0.08 -> 0.02 on real frames at moderate noise.
        """
        return self._angle_from_spectrum(self._spectrum(image, mean))

    def _angle_from_spectrum(self, spectrum: np.ndarray, small_turns: bool = True) -> float:
        """:meth:`estimate_rotation` from the frame's spectrum under the fixed window;
        ``small_turns=False`` skips the second measurement of small turns (for when
        :meth:`refine_rotation` follows: it is not locked at small turns)."""
        log_polar = log_polar_magnitude(spectrum, self.emphasis, self.grid, self._log_magnitude, self._log_polar)
        current = angular_spectrum(log_polar, self.angular_plan)
        # Angles run from -90 (column 0 of the log-polar grid) to +90 degrees with v
        # along rows (down), so a counter-clockwise turn as displayed moves the profile back.
        degrees_per_sample = -180.0 / self.grid.angles
        _kernels.normalized_angular_cross_into(current, self.reference_angular_conjugate[np.newaxis],
                                               self._unit_ramp, self._angular_accumulator, self._angular_cross)
        samples, _ = self.refiner.peak(self._angular_cross)
        angle = samples * degrees_per_sample
        self._first_angular_cross[...] = self._angular_cross
        if small_turns and abs(angle) < self.turned_reference_below_deg:
            # Against each turned copy, normalized (eq. 12), moved back by its known
            # turn and summed: one surface whose peak is the mean of the four estimates.
            _kernels.normalized_angular_cross_into(current, self.turned_reference_angular_conjugates,
                                                   self.turned_reference_ramps, self._angular_accumulator,
                                                   self._angular_cross)
            samples, _ = self.refiner.peak(self._angular_cross)
            angle = samples * degrees_per_sample
        return float(angle)

    def refine_rotation(self, mean: float, angle: float, shift: tuple[float, float],
                        filtered: bool) -> tuple[float, float, tuple[float, float]]:
        """The angle at which the frame correlates best with the reference.

        The log-polar estimate (eq. 9-12) reads the magnitude spectrum only: where that
        is nearly isotropic (round particles, a smooth halo, noise) it wanders by
        tenths of a degree, while the image itself still pins the angle down. So the
        halved frame (``self._half_image``) is registered (the band-limited fit of eq.
        18-22) against copies of the reference turned by whole probes
        (``ROTATION_PROBE_PX``, made once) around the estimate, and the normalized
        correlation at each best shift is kept; a parabola through the best three
        gives the angle. Small turns (``SMALL_TURN_PROBES``) are fitted as they are;
        larger ones are first turned back by the estimate. When the top is not between
        the probes, the copy one probe further out on the higher side is tried too.

        Returns (angle, sharpness, shift at the middle probe, in the axes of the frame
        turned back by ``angle``): ``sharpness`` is the fraction of the correlation
        lost one probe away from the top (0 when there is no top: the image cannot tell
        the angle, e.g. a rotationally symmetric scene).
        """
        probe_deg = self.rotation_probe_deg
        if abs(angle) <= SMALL_TURN_PROBES * probe_deg:
            turned_back, middle = 0.0, int(round(angle / probe_deg))
            frame = self._half_image
        else:
            turned_back, middle = angle, 0
            if self._half_derotated_by != angle:
                rotate_about_centre(self._half_image, -angle, self._half_derotated, PROBE_INTERPOLATION)
                self._half_derotated_by = angle
            frame = self._half_derotated
        dy, dx = shift
        spectrum = self._windowed_half_spectrum(frame, mean, shift)
        band = self.search_filtered_fit_band if filtered else self.search_fit_band
        # The unturned reference's fit starts the others (a turn moves the best shift
        # little: by the turn times the distance from the window's centre).
        best = refine_on_band(spectrum, self.probe_reference_conjugates[0], band, (dy / 2, dx / 2),
                              workspace=self._search_band_workspace, with_correlation=True)
        fits: dict[int, tuple[float, float, float]] = {0: best}

        def correlation(probe: int) -> float:
            if probe not in fits:
                fits[probe] = refine_on_band(spectrum, self.probe_reference_conjugates[probe], band, best[:2],
                                             workspace=self._search_band_workspace, with_correlation=True)
            return fits[probe][2]

        outermost = SMALL_TURN_PROBES + 1
        for _ in range(2):
            if max(correlation(middle - 1), correlation(middle + 1)) <= correlation(middle):
                break
            step = 1 if correlation(middle + 1) > correlation(middle - 1) else -1
            if abs(middle + step) >= outermost:
                break
            middle += step
        below, at, above = correlation(middle - 1), correlation(middle), correlation(middle + 1)
        curvature = below - 2 * at + above
        best_shift = (fits[middle][0] * 2, fits[middle][1] * 2)
        if curvature >= 0 or at < max(below, above):
            return angle, 0.0, shift
        offset = 0.5 * (below - above) / curvature
        top = at - 0.125 * (below - above) ** 2 / curvature
        sharpness = -0.5 * curvature / top if top > 0 else 0.0
        refined = turned_back + (middle + offset) * probe_deg
        if turned_back == 0.0 and abs(refined) > DEROTATE_ABOVE_DEG:
            # The fits were in the frame's own axes; the fit that follows turns it back.
            theta = np.deg2rad(refined)
            y, x = best_shift
            best_shift = (x * np.sin(theta) + y * np.cos(theta), x * np.cos(theta) - y * np.sin(theta))
        return float(refined), float(sharpness), best_shift

    def _halve_into_half_image(self, image: np.ndarray) -> None:
        cv2.resize(image, self.search_shape[::-1], dst=self._half_image, interpolation=cv2.INTER_AREA)
        self._half_derotated_by = None

    def _half_search(self, mean: float, angle: float) -> tuple[tuple[float, float, float, float], np.ndarray]:
        """The whole-pixel search on the halved image turned back by ``angle``: (dy, dx,
        peak height, PSR) and the search spectrum (the plan's buffer)."""
        half = rotate_about_centre(self._half_image, -angle, self._half_derotated, PROBE_INTERPOLATION)
        self._half_derotated_by = angle
        spectrum = self._search_spectrum(half, mean)
        return self._search(spectrum, self.search_reference_conjugate), spectrum

    def _half_fit(self, angle: float, mean: float, shift: tuple[float, float],
                  filtered: bool) -> tuple[float, float, float]:
        """The halved image turned back by ``angle``, fitted on the half-resolution band
        (the window is the full-resolution one moved by the whole-pixel shift, then
        halved, as in :meth:`_fit_fast`): (dy, dx) in full-resolution pixels and the
        normalized correlation there."""
        dy, dx = shift
        half = rotate_about_centre(self._half_image, -angle, self._half_derotated, PROBE_INTERPOLATION)
        self._half_derotated_by = angle
        band = self.search_filtered_fit_band if filtered else self.search_fit_band
        search_dy, search_dx, correlation = refine_on_band(
            self._windowed_half_spectrum(half, mean, shift), self.fit_search_reference_conjugate, band,
            (dy / 2, dx / 2), workspace=self._search_band_workspace, with_correlation=True)
        # Block means are centred half a search pixel in: the shift scales exactly.
        return search_dy * 2, search_dx * 2, correlation

    def _windowed_half_spectrum(self, half: np.ndarray, mean: float, shift: tuple[float, float]) -> np.ndarray:
        """FFT of a halved frame (mean-free) under the full-resolution window moved by the
        whole-pixel ``shift`` and halved, so it weights the scene as the fast fit's
        reference does. The plan's buffer."""
        windowed = self.search_plans.forward.input_array
        np.subtract(half, mean, out=windowed)
        windowed *= self._moved_window_halved(int(round(shift[0])), int(round(shift[1])))
        return self.search_plans.forward()

    def _moved_window_halved(self, row_shift: int, col_shift: int) -> np.ndarray:
        """Block means of the full-resolution window moved by whole pixels (kept per shift:
        a servo loop sees few)."""
        key = (row_shift, col_shift)
        window = self._moved_windows.get(key)
        if window is None:
            if len(self._moved_windows) >= MOVED_WINDOWS_KEPT:
                self._moved_windows.clear()
            window = np.empty(self.search_shape, np.float32)
            _kernels.apodize_halve_into(self._unit_image, 0.0, self.window, row_shift, col_shift,
                                        self._search_scratch, window)
            self._moved_windows[key] = window
        return window

    def _moved_reference_conjugate(self, row_shift: int, col_shift: int) -> np.ndarray:
        """Conjugate spectrum of the reference under the window moved by (-row_shift,
        -col_shift): the frame keeps the fixed window, so the reference's window follows
        the content (kept per shift)."""
        if row_shift == 0 and col_shift == 0:
            return self.reference_conjugate
        key = (row_shift, col_shift)
        conjugate = self._moved_references.get(key)
        if conjugate is None:
            if len(self._moved_references) >= MOVED_WINDOWS_KEPT:
                self._moved_references.clear()
            if self._reference_plans is None:
                self._reference_plans = FFTPlans.for_shape(self.shape, self.fft_effort)
            _kernels.apodize_into(self._reference, self._reference_mean, self.window, -row_shift, -col_shift,
                                  self._reference_plans.forward.input_array)
            conjugate = np.conj(self._reference_plans.forward())
            self._moved_references[key] = conjugate
        return conjugate

    def _search(self, search_spectrum: np.ndarray, reference_conjugate: np.ndarray) -> tuple[float, float, float, float]:
        """Step 1 of the translation: (dy, dx) in full-resolution pixels, peak height and
        PSR from the half-resolution pair (eq. 18-24). Uses the search plans' buffers."""
        weight = self.search_lowpass if self.search_lowpass is not None else self.no_weight
        _kernels.normalized_cross_power_into(search_spectrum, reference_conjugate, weight,
                                             self.search_lowpass is not None, self.search_plans.inverse.input_array)
        surface = self.search_plans.inverse(normalise_idft=True)
        peak_row, peak_col, height, psr = _kernels.peak_and_sidelobe(surface, PSR_EXCLUSION)
        offset_row, offset_col = _kernels.foroosh_offsets(surface, peak_row, peak_col)
        factor = self.search_factor
        dy = (centred_shift(peak_row, self.search_shape[0]) + offset_row) * factor
        dx = (centred_shift(peak_col, self.search_shape[1]) + offset_col) * factor
        return dy, dx, float(height), float(psr)

    def _turned_is_better(self, search_spectrum: np.ndarray, reference_conjugate: np.ndarray) -> bool:
        """Whether the frame turned by 180 degrees matches the reference better than the
        frame as it is: for a real image under a symmetric window the turned spectrum is
        the conjugate (up to a one-pixel shift that does not change the peak height), so
        the two phase-correlation peaks are compared, on the spectra's low-frequency
        quarter (an ideal decimation: plenty to tell a match from none, at a quarter of
        the cost)."""
        quarter = crop_spectrum_into(search_spectrum, self._quarter_spectrum)
        reference = crop_spectrum_into(reference_conjugate, self._quarter_reference)
        heights = []
        for spectrum in (quarter, np.conj(quarter)):
            _kernels.normalized_cross_power_into(spectrum, reference, self.no_weight, False,
                                                 self.quarter_plans.inverse.input_array)
            heights.append(float(self.quarter_plans.inverse(normalise_idft=True).max()))
        return heights[1] > heights[0]

    def _search_full(self, spectrum: np.ndarray) -> tuple[float, float, float, float]:
        """The search on the low-frequency quarter of the full-resolution spectrum."""
        return self._search(crop_spectrum_into(spectrum, self._cropped), self.cropped_reference_conjugate)

    def _fit_full(self, spectrum: np.ndarray, shift: tuple[float, float], filtered: bool) -> tuple[float, float]:
        """Steps 2 and 3 at full resolution: the band-limited correlation maximum of the
        frame's spectrum against the reference under the window moved by the
        whole-pixel shift (:meth:`_moved_reference_conjugate`)."""
        dy, dx = shift
        reference = self._moved_reference_conjugate(int(round(dy)), int(round(dx)))
        band = self.filtered_fit_band if filtered else self.fit_band
        return refine_on_band(spectrum, reference, band, shift, workspace=self._band_workspace)

    def _fit_fast(self, image: np.ndarray, mean: float, shift: tuple[float, float], filtered: bool) -> tuple[float, float]:
        """Steps 2 and 3 on the halved pair (``precision="fast"``): the full-resolution
        window moved by whole full-resolution pixels, then halved, so the scene
        weighting matches to within half a pixel."""
        dy, dx = shift
        if self.search_factor == 1:
            return self._fit_full(self._spectrum(image, mean), shift, filtered)
        _kernels.apodize_halve_into(image, mean, self.window, int(round(dy)), int(round(dx)),
                                    self._search_scratch, self.search_plans.forward.input_array)
        spectrum = self.search_plans.forward()
        band = self.search_filtered_fit_band if filtered else self.search_fit_band
        search_dy, search_dx = refine_on_band(spectrum, self.fit_search_reference_conjugate, band,
                                              (dy / 2, dx / 2), workspace=self._search_band_workspace)
        # Block means are centred half a search pixel in: the shift scales exactly.
        return search_dy * 2, search_dx * 2

    def estimate(self, image, *, rotation: bool | None = None) -> Motion:
        """Motion of ``image`` against the reference. ValueError for bad input.

        ``rotation=False`` skips the rotation measurement of an estimator made with
        rotation (a third of the time, when nothing can turn); None: as made.

        Translation (``precision="full"``, the default):

        1. One FFT of the frame under the fixed window.
        2. Search: the peak of the inverse normalized cross-power spectrum (eq. 18-20)
           over the spectrum's low-frequency quarter (a half-rate grid), sub-pixel by
           Foroosh's neighbour ratio (eq. 21-22), centred (eq. 23-24); its sharpness
           (PSR) gives the confidence.
        3. The sub-pixel shift is the maximum of the band-limited correlation surface
           (:func:`refine_on_band`) against the reference under the window moved by the
           nearest whole-pixel shift, so both images weight the same scene (a window
           fixed on both frames weighs the moved content differently and biases
           towards zero). When the frame is filtered (section II-D, only with a
           ``snr_threshold_db``) the band is weighted by the 5 x 5 Gaussian's transfer
           function.

        ``precision="fast"`` searches and fits on a 2 x 2 block-averaged pair instead.

        Rotation first when on (eq. 9-12, :meth:`estimate_rotation`), from the same
        spectrum; then the search runs on the halved image turned back by it, theta and
        theta + 180 are told apart by the translation peak, the angle is refined on the
        image itself (:meth:`refine_rotation`), and the shift is fitted on the frame
        turned back by the refined angle (at full resolution with ``precision="full"``).
        """
        image, statistics = self._check(image)
        mean = float(statistics[0])
        snr_db = _snr_from(statistics)
        threshold = self.snr_threshold_db
        filtered = threshold is not None and (snr_db < threshold or self.reference_snr_db < threshold)
        if rotation and not self.rotation:
            raise ValueError("this estimator was made without rotation (rotation=False)")
        if self.rotation and rotation is not False:
            return self._estimate_with_rotation(image, mean, snr_db, filtered)
        if self.precision == "full":
            spectrum = self._spectrum(image, mean)
            dy, dx, height, psr = self._search_full(spectrum)
            shift = self._fit_full(spectrum, (dy, dx), filtered)
        else:
            dy, dx, height, psr = self._search(self._search_spectrum_of(image, mean), self.search_reference_conjugate)
            shift = self._fit_fast(image, mean, (dy, dx), filtered)
        return _motion(shift, 0.0, False, height, psr, snr_db, filtered)

    def _estimate_with_rotation(self, image: np.ndarray, mean: float, snr_db: float, filtered: bool) -> Motion:
        spectrum = self._spectrum(image, mean)
        angle = self._angle_from_spectrum(spectrum, small_turns=self.search_factor == 1)
        if self.search_factor == 1:
            return self._estimate_small_with_rotation(image, mean, angle, snr_db, filtered)
        self._halve_into_half_image(image)
        result = self._turn_from(image, mean, spectrum, angle, filtered)
        if result[1] == 0.0:
            # No top near the log-polar peak: the magnitude spectrum's strongest peak can
            # be the scene's axis-aligned edges or the window's (a turn near 90 degrees
            # read as 0). Its next peaks are tried, each verified on the image.
            degrees_per_sample = -180.0 / self.grid.angles
            for samples in angular_candidates(self._first_angular_cross, self.grid.angles, ANGLE_CANDIDATES)[1:]:
                candidate = self._turn_from(image, mean, spectrum, samples * degrees_per_sample, filtered)
                if candidate[1] > 0.0:
                    result = candidate
                    break
        return self._fit_turned(image, mean, spectrum, *result, snr_db, filtered)

    def _turn_from(self, image: np.ndarray, mean: float, spectrum: np.ndarray, angle: float,
                   filtered: bool) -> tuple[float, float, tuple[float, float], float, float]:
        """From a log-polar angle: the search (theta or theta + 180) and the refinement.
        Returns (angle, sharpness, shift, search peak height, PSR)."""
        if abs(angle) <= SMALL_TURN_PROBES * self.rotation_probe_deg:
            # A turn this small moves no pixel by more than SMALL_TURN_PROBES: the
            # whole-pixel search does not need the frame turned back.
            (dy, dx, height, psr), searched = self._search_full(spectrum), self._cropped
            reference = self.cropped_reference_conjugate
        else:
            (dy, dx, height, psr), searched = self._half_search(mean, angle)
            reference = self.search_reference_conjugate
        # theta or theta + 180? The magnitude spectrum cannot tell; the translation
        # peak can: compare it with the peak of the image turned by 180 degrees.
        if self._turned_is_better(searched, reference):
            angle += 180.0 if angle < 0 else -180.0
            (dy, dx, height, psr), _ = self._half_search(mean, angle)
        angle, sharpness, shift = self.refine_rotation(mean, angle, (dy, dx), filtered)
        return angle, sharpness, shift, height, psr

    def _fit_turned(self, image: np.ndarray, mean: float, spectrum: np.ndarray, angle: float, sharpness: float,
                    shift: tuple[float, float], height: float, psr: float, snr_db: float, filtered: bool) -> Motion:
        """The final fit of the frame turned back by the refined ``angle`` (``spectrum``:
        the frame's own, used as it is below ``DEROTATE_ABOVE_DEG``)."""
        rotation_confidence = confidence_from_sharpness(sharpness)
        if self.precision == "fast":
            return _motion(self._half_fit(angle, mean, shift, filtered)[:2], angle, True, height, psr, snr_db,
                           filtered, rotation_confidence)
        derotated = abs(angle) > DEROTATE_ABOVE_DEG
        if derotated:
            spectrum = self._spectrum(rotate_about_centre(image, -angle, self._derotated), mean)
        return _motion(self._fit_full(spectrum, shift, filtered), angle, derotated, height, psr, snr_db, filtered,
                       rotation_confidence)

    def _estimate_small_with_rotation(self, image: np.ndarray, mean: float, angle: float, snr_db: float,
                                      filtered: bool) -> Motion:
        """Images under 128 pixels a side have no halved pair: the log-polar angle is
        used as it is (not refined), the search and the fit run at full resolution."""
        derotated = abs(angle) > DEROTATE_ABOVE_DEG
        turned = rotate_about_centre(image, -angle, self._derotated) if derotated else image
        spectrum = self._spectrum(turned, mean)
        dy, dx, height, psr = self._search_full(spectrum)
        if self._turned_is_better(self._cropped, self.cropped_reference_conjugate):
            angle += 180.0 if angle < 0 else -180.0
            derotated = True
            spectrum = self._spectrum(rotate_about_centre(image, -angle, self._derotated), mean)
            dy, dx, height, psr = self._search_full(spectrum)
        return _motion(self._fit_full(spectrum, (dy, dx), filtered), angle, derotated, height, psr, snr_db, filtered)
