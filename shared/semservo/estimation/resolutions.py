"""The reference as :class:`~semservo.estimation.MotionEstimator` keeps it: one small
structure per resolution, each holding what depends only on the reference (window,
spectra, FFT plans, fit bands), made once, beside the per-frame buffers that the steps
reading it reuse (large temporaries would cost page faults on every frame).

* :class:`FullResolution`: the frame's own pixels. The sub-pixel fit (section II-C, eq.
  18-22 as a phase-plane fit) and the rotation's spectrum (section II-B-1) read it.
* :class:`HalfResolution`: the pair halved (2 x 2). The whole-pixel search (eq. 18-24),
  ``precision="fast"``'s fit, theta told from theta + 180 degrees, and the rotation's
  refinement on the image.

An estimator is not thread-safe: these buffers are reused from frame to frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from semservo.estimation import _kernels
from semservo.estimation.common import MIN_SIZE, apodization_window
from semservo.estimation.plans import FFTPlans
from semservo.estimation.snr import gaussian_lowpass, gaussian_transfer
from semservo.estimation.translation import (
    PSR_EXCLUSION, BandFit, PhasePlaneBand, Shift, centred_shift, crop_spectrum_into, refine_on_band,
)

#: How many moved windows (or reference spectra under them), one per whole-pixel shift,
#: an estimator keeps: a servo loop sees few shifts.
MOVED_WINDOWS_KEPT = 64


def weighted_spectrum(plans, image: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """FFT of ``image`` under ``weights``, less its weighted mean (so the weights' own
    spectrum does not leak into the band), through ``plans`` (its buffer: copy to keep)."""
    total = float(weights.sum())
    mean = float(np.vdot(image, weights)) / total if total > 0 else 0.0
    _kernels.apodize_into(image, mean, weights, 0, 0, plans.forward.input_array)
    return plans.forward()


class Search(NamedTuple):
    """The whole-pixel search's answer (eq. 18-24): the shift in full-resolution pixels
    (sub-pixel by Foroosh's ratio), the correlation peak's height and its
    peak-to-sidelobe ratio (the confidence's source)."""

    dy: float
    dx: float
    height: float
    psr: float

    @property
    def shift(self) -> Shift:
        return Shift(self.dy, self.dx)


#: The sub-pixel fit starts at the search's peak, within about a pixel wherever the search
#: is right (a half-resolution peak and its neighbours); a fit that ends further than
#: this (pixels, along either axis) has climbed a sidelobe of a noisy correlation surface
#: (seen on a real frame at a fifth of its contrast and 100 electrons per grey level: 3 px
#: off a right search). The fit weighted by the prefilter is smoother and is allowed twice
#: as far.
MAX_FIT_MOVE_PX = 1.0


def kept_near(start: Shift, fitted, band: PhasePlaneBand, filtered_band: PhasePlaneBand) -> Shift:
    """``fitted(band)``, unless it ends more than ``MAX_FIT_MOVE_PX`` from ``start``: then
    the fit on the band weighted by the 5 x 5 Gaussian's transfer function (section II-D:
    noisy frequencies count less), unless that ends more than twice as far; then
    ``start``."""
    attempts = ((band, MAX_FIT_MOVE_PX),) if band is not filtered_band else ()
    attempts += ((filtered_band, 2 * MAX_FIT_MOVE_PX),)
    for weighting, limit in attempts:
        shift = fitted(weighting)
        if max(abs(shift.dy - start[0]), abs(shift.dx - start[1])) <= limit:
            return shift
    return Shift(float(start[0]), float(start[1]))


class HalfTurnHeights(NamedTuple):
    """The phase-correlation peaks of a frame and of the frame turned by 180 degrees
    against the reference (:meth:`HalfResolution.half_turn_heights`)."""

    as_is: float
    turned: float

    @property
    def turned_is_better(self) -> bool:
        return self.turned > self.as_is

    @property
    def best(self) -> float:
        return max(self.as_is, self.turned)

    @property
    def decisive(self) -> float:
        """How clearly one wins: the higher peak over the lower (1: no telling)."""
        return max(self.as_is, self.turned) / max(min(self.as_is, self.turned), 1e-12)


@dataclass
class FullResolution:
    """The frame's own resolution: the window, the FFT plans, the reference's conjugate
    spectrum (under the fixed window, and under windows moved by whole-pixel shifts,
    kept per shift) and the sub-pixel fit's bands (plain, and weighted by the 5 x 5
    Gaussian prefilter's transfer function for filtered frames, section II-D)."""

    shape: tuple[int, int]
    window: np.ndarray
    plans: FFTPlans
    fft_effort: str
    reference: np.ndarray
    reference_mean: float
    reference_conjugate: np.ndarray
    fit_band: PhasePlaneBand
    filtered_fit_band: PhasePlaneBand
    band_workspace: np.ndarray
    moved_references: dict[tuple[int, int], np.ndarray] = field(default_factory=dict)
    #: Plans of their own for the moved references (the frame's spectrum stays in
    #: ``plans``' buffer meanwhile); made at the first moved window.
    reference_plans: FFTPlans | None = None
    #: The frame turned back by its rotation (made at the first turn).
    turned_back_buffer: np.ndarray | None = None
    #: Whether the fit must end near the search's peak (:func:`kept_near`); not against
    #: a mask, whose low-pass correlation peaks broadly and legitimately far from it.
    near_search: bool = True

    @classmethod
    def of(cls, reference: np.ndarray, window: str, band: float, lowpass: np.ndarray | None,
           fft_effort: str) -> "FullResolution":
        """``lowpass``: the mask's spectral weight (paper case 6), or None."""
        shape = reference.shape
        prefilter = gaussian_transfer(shape)
        filtered_weight = prefilter if lowpass is None else prefilter * lowpass
        fit_band = PhasePlaneBand.for_shape(shape, band, extra_weight=lowpass)
        full = cls(shape=shape, window=apodization_window(shape, window), plans=FFTPlans.for_shape(shape, fft_effort),
                   fft_effort=fft_effort, reference=reference, reference_mean=float(reference.mean()),
                   reference_conjugate=np.empty(0, np.complex64), fit_band=fit_band,
                   filtered_fit_band=PhasePlaneBand.for_shape(shape, band, extra_weight=filtered_weight),
                   band_workspace=np.empty(fit_band.weights.shape, np.complex128), near_search=lowpass is None)
        full.reference_conjugate = np.conj(full.spectrum(reference, float(reference.mean())))
        return full

    def spectrum(self, image: np.ndarray, mean: float, row_shift: int = 0, col_shift: int = 0) -> np.ndarray:
        """FFT of the mean-free image under the window moved by (row_shift, col_shift),
        written straight into the plan's input; the result is the plan's buffer."""
        _kernels.apodize_into(image, mean, self.window, row_shift, col_shift, self.plans.forward.input_array)
        return self.plans.forward()

    def moved_reference_conjugate(self, row_shift: int, col_shift: int) -> np.ndarray:
        """Conjugate spectrum of the reference under the window moved by (-row_shift,
        -col_shift): the frame keeps the fixed window, so the reference's window follows
        the content (kept per shift)."""
        if row_shift == 0 and col_shift == 0:
            return self.reference_conjugate
        key = (row_shift, col_shift)
        conjugate = self.moved_references.get(key)
        if conjugate is None:
            if len(self.moved_references) >= MOVED_WINDOWS_KEPT:
                self.moved_references.clear()
            if self.reference_plans is None:
                self.reference_plans = FFTPlans.for_shape(self.shape, self.fft_effort)
            _kernels.apodize_into(self.reference, self.reference_mean, self.window, -row_shift, -col_shift,
                                  self.reference_plans.forward.input_array)
            conjugate = np.conj(self.reference_plans.forward())
            self.moved_references[key] = conjugate
        return conjugate

    def fit(self, spectrum: np.ndarray, shift: Shift, filtered: bool, search_distinct: bool = True) -> Shift:
        """Steps 2 and 3 at full resolution: the band-limited correlation maximum of the
        frame's spectrum against the reference under the window moved by the
        whole-pixel shift (:meth:`moved_reference_conjugate`), near ``shift`` (see
        :func:`kept_near`) when the search's peak was distinct (``search_distinct``): a
        search peak no sharper than the noise's is no anchor, and the fit, which weighs
        the frequencies by their magnitude, finds the shift the phase-only search missed
        (a smooth scene at 2 dB: the search 4.6 px off, the fit within 0.05 px)."""
        dy, dx = shift
        reference = self.moved_reference_conjugate(int(round(dy)), int(round(dx)))

        def fitted(band: PhasePlaneBand) -> Shift:
            fit = refine_on_band(spectrum, reference, band, shift, workspace=self.band_workspace)
            return Shift(fit.dy, fit.dx)

        band = self.filtered_fit_band if filtered else self.fit_band
        if not (self.near_search and search_distinct):
            return fitted(band)
        return kept_near(shift, fitted, band, self.filtered_fit_band)

    def weighted_spectrum(self, image: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """FFT of a full-resolution image under ``weights`` (:func:`weighted_spectrum`)."""
        return weighted_spectrum(self.plans, image, weights)

    def frame_buffer(self) -> np.ndarray:
        """A frame-sized buffer (for the frame turned back by its rotation), made once."""
        if self.turned_back_buffer is None:
            self.turned_back_buffer = np.empty(self.shape, np.float32)
        return self.turned_back_buffer


@dataclass
class HalfResolution:
    """The halved pair (``factor`` 2; 1 for images under ``2 * MIN_SIZE`` a side, which
    are searched at full resolution): the whole-pixel search (eq. 18-24) on the reference
    halved by a binomial filter under its own window, the fast fit's reference (the
    full-resolution window applied before halving), and the search on the frame's
    full-resolution spectrum's low-frequency quarter (``cropped_*``)."""

    factor: int
    shape: tuple[int, int]
    window: np.ndarray
    plans: FFTPlans
    #: The full-resolution window: the fits move it by whole full-resolution pixels.
    full_window: np.ndarray
    reference_conjugate: np.ndarray
    #: The mask's low-pass at this resolution (None without a mask).
    lowpass: np.ndarray | None
    fit_reference_conjugate: np.ndarray
    fit_band: PhasePlaneBand
    filtered_fit_band: PhasePlaneBand
    cropped_reference_conjugate: np.ndarray
    # Per-frame buffers.
    scratch: np.ndarray  # (full rows, half columns): the halving's first pass
    block: np.ndarray
    cropped: np.ndarray
    band_workspace: np.ndarray
    moved_windows: dict[tuple[int, int], np.ndarray] = field(default_factory=dict)
    no_weight: np.ndarray = field(default_factory=lambda: np.ones((1, 1), np.float32))

    @classmethod
    def of(cls, full: FullResolution, window: str, band: float, mask_band: float | None) -> "HalfResolution":
        """``mask_band``: the mask's low-pass width in full-resolution cycles/pixel, or None."""
        factor = 2 if min(full.shape) >= 2 * MIN_SIZE else 1
        shape = (full.shape[0] // factor, full.shape[1] // factor)
        plans = FFTPlans.for_shape(shape, full.fft_effort)
        # The fit band is in cycles per pixel of the image it applies to; the mask's
        # low-pass and the prefilter are physical, so they scale with the factor.
        lowpass = gaussian_lowpass(shape, mask_band * factor) if mask_band is not None else None
        spectrum_shape = (shape[0], shape[1] // 2 + 1)
        half = cls(
            factor=factor, shape=shape, window=apodization_window(shape, window), plans=plans,
            full_window=full.window, reference_conjugate=np.empty(0, np.complex64), lowpass=lowpass,
            fit_reference_conjugate=np.empty(0, np.complex64),
            fit_band=PhasePlaneBand.for_shape(shape, band, extra_weight=lowpass),
            filtered_fit_band=PhasePlaneBand.for_shape(
                shape, band, extra_weight=gaussian_transfer(shape, sigma=1.0 / factor) * (1 if lowpass is None
                                                                                          else lowpass)),
            cropped_reference_conjugate=np.empty(spectrum_shape, np.complex64),
            scratch=np.empty((full.shape[0], shape[1]), np.float32), block=np.empty(shape, np.float32),
            cropped=np.empty(spectrum_shape, np.complex64), band_workspace=np.empty(0, np.complex128),
        )
        half.band_workspace = np.empty(half.fit_band.weights.shape, np.complex128)
        halved = half.halve(full.reference)
        half.reference_conjugate = np.conj(half.spectrum(halved, float(halved.mean())))
        half.fit_reference_conjugate = np.conj(half.apodized_spectrum(full.reference, full.reference_mean, 0, 0))
        crop_spectrum_into(full.reference_conjugate, half.cropped_reference_conjugate)
        return half

    def halve(self, image: np.ndarray) -> np.ndarray:
        """The search image of ``image`` (a copy in a new array; used once per reference)."""
        if self.factor == 1:
            return np.array(image, dtype=np.float32)
        halved = np.empty(self.shape, np.float32)
        _kernels.decimate_apodize_into(np.ascontiguousarray(image, dtype=np.float32), 0.0,
                                       np.ones(self.shape, np.float32), self.scratch, halved,
                                       np.empty(self.shape, np.float32))
        return halved

    def spectrum(self, halved: np.ndarray, mean: float) -> np.ndarray:
        """FFT of a mean-free, apodized image of this resolution; the plan's buffer."""
        _kernels.apodize_into(halved, mean, self.window, 0, 0, self.plans.forward.input_array)
        return self.plans.forward()

    def spectrum_of(self, image: np.ndarray, mean: float) -> np.ndarray:
        """Halve a full-resolution ``image`` into ``block`` and return the FFT of its
        mean-free, apodized version (the plan's buffer), in one fused pass."""
        if self.factor == 1:
            self.block[...] = image
            return self.spectrum(self.block, mean)
        _kernels.decimate_apodize_into(image, mean, self.window, self.scratch, self.block,
                                       self.plans.forward.input_array)
        return self.plans.forward()

    def apodized_spectrum(self, image: np.ndarray, mean: float, row_shift: int, col_shift: int) -> np.ndarray:
        """FFT of a full-resolution ``image``, mean-free, under the full-resolution window
        moved by whole pixels, then halved by block means (the fast fit's weighting);
        the plan's buffer."""
        _kernels.apodize_halve_into(image, mean, self.full_window, row_shift, col_shift, self.scratch,
                                    self.plans.forward.input_array)
        return self.plans.forward()

    def search(self, spectrum: np.ndarray, reference_conjugate: np.ndarray) -> Search:
        """Step 1 of the translation: the peak of the inverse normalized cross-power
        spectrum (eq. 18-20) of a spectrum of this resolution's shape, sub-pixel by
        Foroosh's neighbour ratio (eq. 21-22), centred (eq. 23-24), in full-resolution
        pixels. Uses the plans' inverse buffer."""
        weight = self.lowpass if self.lowpass is not None else self.no_weight
        _kernels.normalized_cross_power_into(spectrum, reference_conjugate, weight, self.lowpass is not None,
                                             self.plans.inverse.input_array)
        surface = self.plans.inverse(normalise_idft=True)
        peak_row, peak_col, height, psr = _kernels.peak_and_sidelobe(surface, PSR_EXCLUSION)
        offset_row, offset_col = _kernels.foroosh_offsets(surface, peak_row, peak_col)
        dy = (centred_shift(peak_row, self.shape[0]) + offset_row) * self.factor
        dx = (centred_shift(peak_col, self.shape[1]) + offset_col) * self.factor
        return Search(dy, dx, float(height), float(psr))

    def search_full(self, full_spectrum: np.ndarray) -> Search:
        """The search on the low-frequency quarter of a full-resolution spectrum (an
        ideal decimation, see :func:`crop_spectrum_into`); the quarter stays in
        ``cropped``."""
        return self.search(crop_spectrum_into(full_spectrum, self.cropped), self.cropped_reference_conjugate)

    def fit(self, spectrum: np.ndarray, reference_conjugate: np.ndarray, shift: tuple[float, float], filtered: bool,
            with_correlation: bool = False) -> BandFit:
        """The band-limited fit (:func:`refine_on_band`) of a spectrum of this resolution
        from the full-resolution ``shift``; the answer in full-resolution pixels."""
        band = self.filtered_fit_band if filtered else self.fit_band
        fit = refine_on_band(spectrum, reference_conjugate, band, (shift[0] / 2, shift[1] / 2),
                             workspace=self.band_workspace, with_correlation=with_correlation)
        # Block means are centred half a search pixel in: the shift scales exactly.
        return BandFit(fit.dy * 2, fit.dx * 2, fit.correlation)

    def half_turn_heights(self, search_spectrum: np.ndarray, reference_conjugate: np.ndarray,
                          as_is: float | None = None) -> "HalfTurnHeights":
        """How well the frame as it is and the frame turned by 180 degrees match the
        reference: for a real image under a symmetric window the turned spectrum is the
        conjugate (up to a one-pixel shift that does not change the peak height), so the
        two phase-correlation peaks of a spectrum of this resolution are compared. (On
        the spectra's low-frequency quarter, as before, a scene dominated by a centrally
        symmetric shape, a hole's disc, chose the wrong one when the view had moved by a
        fifth of the field: the detail that tells them apart is above that band.)
        ``as_is``: the frame's own peak when the search has just measured it on these
        spectra (its height). Uses the plans' inverse buffer."""
        heights = []
        for spectrum in ((search_spectrum,) if as_is is None else ()) + (np.conj(search_spectrum),):
            _kernels.normalized_cross_power_into(spectrum, reference_conjugate, self.no_weight, False,
                                                 self.plans.inverse.input_array)
            heights.append(float(self.plans.inverse(normalise_idft=True).max()))
        return HalfTurnHeights(*([as_is] if as_is is not None else []), *heights)

    def moved_window(self, row_shift: int, col_shift: int) -> np.ndarray:
        """Block means of the full-resolution window moved by whole pixels (kept per
        shift: a servo loop sees few)."""
        key = (row_shift, col_shift)
        window = self.moved_windows.get(key)
        if window is None:
            if len(self.moved_windows) >= MOVED_WINDOWS_KEPT:
                self.moved_windows.clear()
            window = np.empty(self.shape, np.float32)
            unit = np.ones(self.full_window.shape, np.float32)
            _kernels.apodize_halve_into(unit, 0.0, self.full_window, row_shift, col_shift, self.scratch, window)
            self.moved_windows[key] = window
        return window

    def band_signal_fraction(self, spectrum: np.ndarray, weights: np.ndarray, noise_variance: float,
                             filtered: bool) -> float:
        """The share of a spectrum's power in the fit band that is signal, not pixel
        noise: white noise of ``noise_variance`` (per pixel of this resolution) under
        the spatial ``weights`` puts noise_variance x sum(weights^2) into every
        frequency, so 1 - that times the band's weights over the band's power. Two
        noisy views of one scene correlate at most by the square root of the product
        of their fractions."""
        band = self.filtered_fit_band if filtered else self.fit_band
        power = _kernels.band_power(spectrum, band.rows, band.weights)
        noise = noise_variance * float(np.vdot(weights, weights)) * band.total_weight
        return max(0.0, 1.0 - noise / power) if power > 0 else 0.0

    def weighted_spectrum(self, halved: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """FFT of an image of this resolution under ``weights`` (:func:`weighted_spectrum`)."""
        return weighted_spectrum(self.plans, halved, weights)

    def windowed_spectrum(self, halved: np.ndarray, mean: float, shift: Shift) -> np.ndarray:
        """FFT of a halved frame (mean-free) under the full-resolution window moved by the
        whole-pixel ``shift`` and halved, so it weights the scene as the fast fit's
        reference does. The plan's buffer."""
        windowed = self.plans.forward.input_array
        np.subtract(halved, mean, out=windowed)
        windowed *= self.moved_window(int(round(shift[0])), int(round(shift[1])))
        return self.plans.forward()
