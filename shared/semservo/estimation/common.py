"""What every section of the estimator shares: the result (:class:`Motion`), the input
checks, and the apodization window applied before every FFT (section II-A).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

MIN_SIZE = 64


cv2.setNumThreads(1)  # one core per estimate; the services parallelise across processes


@dataclass(frozen=True)
class Motion:
    """Motion of the current image against the reference (sign convention: :mod:`semservo.estimation`)."""

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
    #: The first of the frame's rows the estimate was measured on (0: the whole frame; a
    #: partial frame leaves out the rows scanned while the stage still moved, see
    #: :meth:`MotionEstimator.estimate`).
    first_row: int = 0

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
            "first_row": self.first_row,
        }


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
