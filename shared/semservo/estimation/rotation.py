"""Rotation about the beam (Marturi et al., section II-B-1, eq. 9-12): the high-pass
log-polar magnitude spectrum, the angular correlation and its peaks, turning an image
about its centre, and the constants of the refinement on the image itself
(:meth:`semservo.estimation.MotionEstimator.refine_rotation`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import pyfftw

from semservo import _kernels
from semservo.estimation.translation import centred_shift

#: Small turns are measured against copies of the reference turned by these angles
#: (degrees), see :meth:`semservo.estimation.MotionEstimator.estimate_rotation`.
TURNED_REFERENCE_DEG = (1.5, -1.5, 3.0, -3.0)
#: The angle from the log-polar spectrum is refined by probe turns that move the edge of
#: the image's inscribed circle by this many pixels either way (see
#: :meth:`semservo.estimation.MotionEstimator.refine_rotation`): about where the correlation has fallen by
#: a measurable amount without leaving its parabolic top.
ROTATION_PROBE_PX = 1.0
#: Turns up to this many probes are refined without turning the frame back: it is fitted
#: straight against reference copies turned by whole probes. Turning the frame back by a
#: small angle with OpenCV's bicubic (or bilinear) kernel turns it by a slightly
#: different angle (the kernel's phase error at small sub-pixel moves: 0.3 degree turned
#: back acted as 0.34), which no probe could correct.
SMALL_TURN_PROBES = 3
#: How many peaks of the log-polar correlation are tried, highest first, when the image
#: shows no correlation top near the highest (see ``MotionEstimator._estimate_with_rotation``).
ANGLE_CANDIDATES = 4
#: Bicubic for the turned images the angle is refined on: bilinear interpolation blurs
#: by an amount that depends on the turn (none at 0 and 90 degrees), which pulled the
#: refined angle towards those (0.05 degree mean error on a sparse scene, 0.008 bicubic).
PROBE_INTERPOLATION = cv2.INTER_CUBIC
#: The rotation's sharpness (see :meth:`semservo.estimation.MotionEstimator.refine_rotation`) at which its
#: confidence is 1 - 1/e. Real SEM scenes lose 4e-4 to 2e-2 of their correlation when a
#: turn moves the image's edge by a pixel (six images of five instruments, at every
#: dose tried); a rotationally symmetric scene (a disc, a ring) loses under 3e-5, so
#: its angle is refused (confidence under 0.25) rather than guessed.
SHARPNESS_SCALE = 1e-4


def confidence_from_sharpness(sharpness: float) -> float:
    """Map the rotation's sharpness to [0, 1]: ``1 - exp(-sharpness / SHARPNESS_SCALE)``."""
    return float(1.0 - np.exp(-max(sharpness, 0.0) / SHARPNESS_SCALE))


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
