"""Translation (Marturi et al., section II-C, eq. 18-24): the normalized cross-power
spectrum, its peak to a fraction of a pixel, and the peak-to-sidelobe ratio the
confidence comes from.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from semservo.estimation import _kernels

#: Sidelobe exclusion half-width for the peak-to-sidelobe ratio (an 11 x 11 box).
PSR_EXCLUSION = 5


class Shift(NamedTuple):
    """A displacement in pixels, rows first as numpy indexes (sign convention:
    :mod:`semservo.estimation`)."""

    dy: float
    dx: float


class BandFit(NamedTuple):
    """:func:`refine_on_band`'s answer: the sub-pixel shift and, when asked for, the
    normalized correlation there (NaN when not)."""

    dy: float
    dx: float
    correlation: float


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


@dataclass(frozen=True)
class PhasePlaneBand:
    """The part of the half-plane spectrum the sub-pixel fit uses: frequencies up to
    ``band`` cycles/pixel (a disc), as a list of spectrum rows times the first columns,
    with a weight per element (the disc, times any extra spectral weight)."""

    rows: np.ndarray  # spectrum row indices in the band
    frequency_rows: np.ndarray  # cycles/pixel of those rows
    frequency_cols: np.ndarray  # cycles/pixel of the first columns
    weights: np.ndarray  # (rows, cols)

    @property
    def total_weight(self) -> float:
        return float(self.weights.sum())

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
                   workspace: np.ndarray | None = None, with_correlation: bool = False) -> BandFit:
    """Sub-pixel shift (dy, dx) by Newton's method on the band-limited correlation surface.

    The cross-power spectrum C = G conj(F) has phase -2 pi (u dx + v dy) (eq. 18), so
    f(d) = Re sum_k w(k) C(k) e^{i 2 pi k.d} (the magnitude-weighted phase correlation
    of eq. 19, evaluated at a continuous shift d) peaks at the true shift. Starting
    from the peak of eq. 20-22, a few Newton steps on f's analytic gradient and Hessian
    find that maximum: the continuous equivalent of an upsampled DFT around the peak,
    at the cost of a few sums over the band and with no grid to quantize the result.
    This is also the paper's "first way" of solving eq. 18, the fit of the phase plane,
    weighted by the spectral magnitude.

    Returns :class:`BandFit` (dy, dx, correlation): with ``with_correlation`` the
    normalized cross-correlation of the band-limited images at that shift (1 for a
    noise-free copy moved by a whole number of pixels), else NaN.
    """
    if workspace is None:
        workspace = np.empty(band.weights.shape, np.complex128)
    dy, dx, _, correlation = _kernels.newton_on_band(
        current_spectrum, reference_conjugate, band.rows, band.frequency_rows, band.frequency_cols,
        band.weights, float(shift[0]), float(shift[1]), iterations, tolerance, workspace, with_correlation,
    )
    return BandFit(dy, dx, correlation if with_correlation else float("nan"))
