"""Image noise (Marturi et al., section II-D): a frame's signal-to-noise ratio, and the
5 x 5 Gaussian that filters frames below a threshold.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from semservo.estimation import _kernels
from semservo.estimation.common import MIN_SIZE

#: Below this SNR (dB) a frame is filtered with the 5 x 5 Gaussian (section II-D); None:
#: never. Not the paper's 15 dB: the magnitude-weighted fit already gives noisy
#: frequencies little weight, and the fixed Gaussian also removes the mid frequencies that
#: carry a sparse scene's edges (held-out images at 13-16 dB: 0.022 -> 0.036 px on a hole
#: at low magnification, 0.023 -> 0.031 px on the drift image). Far below, the unweighted
#: fit climbs sidelobes of the noise: a real frame at a fifth of its contrast and 100
#: electrons per grey level (0 dB) read a shift 3 px off where the search was right, and
#: 0.13 px filtered; on the smooth FIB-SEM slice (2 dB at every dose tried) filtering
#: gains 0.001 px. So frames (or references) under 6 dB are filtered.
DEFAULT_SNR_THRESHOLD_DB: float | None = 6.0


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
    return snr_from_statistics(frame_statistics(image))


class FrameStatistics(NamedTuple):
    """One pass over a frame (:func:`frame_statistics`): its mean and finiteness (whole
    frame), and the autocorrelation of the mean-free frame at lags 0, 1 and 2 down the
    rows and along them (central rows), which the SNR is computed from."""

    mean: float
    finite: bool
    zero_lag: float
    down1: float
    down2: float
    along1: float
    along2: float


def frame_statistics(image: np.ndarray) -> FrameStatistics:
    """:class:`FrameStatistics` of a contiguous float32 ``image`` (one fused pass); the
    autocorrelation over the central half of the rows when the image is tall enough."""
    rows = image.shape[0]
    first, last = (rows // 4, rows - rows // 4) if rows >= 4 * MIN_SIZE else (0, rows)
    return FrameStatistics(*_kernels.frame_statistics(image, first, last))


def _signal_and_noise(statistics: FrameStatistics) -> tuple[float, float]:
    """(signal, noise) variances per pixel (:func:`estimate_snr_db`'s split)."""
    zero_lag, down1, down2, along1, along2 = (statistics.zero_lag, statistics.down1, statistics.down2,
                                              statistics.along1, statistics.along2)
    signal = ((4 * down1 - down2) / 3 + (4 * along1 - along2) / 3) / 2
    signal = min(max(signal, 1e-12 * zero_lag), zero_lag)
    return signal, max(zero_lag - signal, 1e-12 * zero_lag)


def snr_from_statistics(statistics: FrameStatistics) -> float:
    """The SNR in dB (:func:`estimate_snr_db`) from a frame's statistics."""
    if statistics.zero_lag <= 0:
        return float("-inf")
    signal, noise = _signal_and_noise(statistics)
    return float(10 * np.log10(signal / noise))


def noise_variance(statistics: FrameStatistics) -> float:
    """The pixel noise's variance (grey levels squared) from a frame's statistics: what
    the zero-lag autocorrelation holds beyond the signal extrapolated from lags 1 and 2."""
    if statistics.zero_lag <= 0:
        return 0.0
    return float(_signal_and_noise(statistics)[1])


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
