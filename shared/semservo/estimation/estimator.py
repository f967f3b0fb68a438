""":class:`MotionEstimator`: the sections composed. Everything that depends only on the
reference (window, spectra, log-polar reference, turned references, FFT plans) is
computed once, one structure per resolution (:mod:`.resolutions`, and the rotation's
:class:`~.rotation.LogPolarReference` and :class:`~.rotation.ProbeReferences`);
:meth:`MotionEstimator.estimate` runs the per-frame part: rotation (:mod:`.rotation`),
then translation (:mod:`.translation`), with the SNR monitored (:mod:`.snr`). Sign
convention and confidence: :mod:`semservo.estimation`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from semservo.estimation.common import Motion, as_image
from semservo.estimation.masks import mask_reference
from semservo.estimation.resolutions import FullResolution, HalfResolution, QuarterResolution, Search
from semservo.estimation.rotation import (
    ANGLE_CANDIDATES, SMALL_TURN_PROBES, LogPolarReference, ProbeReferences, confidence_from_sharpness, probe_top,
    rotate_about_centre,
)
from semservo.estimation.snr import (
    DEFAULT_SNR_THRESHOLD_DB, FrameStatistics, estimate_snr_db, frame_statistics, gaussian_lowpass,
    snr_from_statistics,
)
from semservo.estimation.translation import Shift, confidence_from_psr

#: Turns smaller than this are not undone before measuring translation (they are still
#: reported): a rotation about the image centre adds no net shift, and undoing a turn
#: at the rotation estimate's noise floor (0.02-0.03 degree on real frames) costs a
#: resampling (0.4 ms) and adds interpolation. Larger turns are undone: on real frames,
#: skipping a 0.1 degree turn moves the shift by up to 0.06 px, a 0.05 degree turn by
#: about 0.02 px.
DEROTATE_ABOVE_DEG = 0.05


class Refined(NamedTuple):
    """The angle refined on the image (``MotionEstimator._refine_rotation``): the angle,
    its sharpness (0: no top, the image cannot tell the angle) and the shift at the
    best probe, in the axes of the frame turned back by the angle."""

    angle: float
    sharpness: float
    shift: Shift


class Turn(NamedTuple):
    """One candidate angle carried through: refined, with the whole-pixel search that
    started its refinement (whose peak gives the confidence)."""

    angle: float
    sharpness: float
    shift: Shift
    search: Search


def _motion(shift: Shift, angle: float, derotated: bool, search: Search, snr_db: float, filtered: bool,
            rotation_confidence: float = 1.0) -> Motion:
    """The estimate, its shift turned back into the current image's axes when it was
    measured on the de-rotated image (counter-clockwise as displayed, rows down)."""
    dy, dx = shift
    if derotated:
        theta = np.deg2rad(angle)
        dx, dy = dx * np.cos(theta) + dy * np.sin(theta), -dx * np.sin(theta) + dy * np.cos(theta)
    return Motion(dx=float(dx), dy=float(dy), rotation_deg=float(angle),
                  confidence=min(confidence_from_psr(search.psr), rotation_confidence), snr_db=float(snr_db),
                  peak=search.height, psr=float(search.psr), filtered=bool(filtered),
                  rotation_confidence=float(rotation_confidence))


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

    Every Motion carries ``rotation_confidence``: how well the image pins the angle down
    (the refinement on the image, see :meth:`estimate`); a scene whose turns all look
    alike is refused.

    Attributes lab scripts read: ``shape``, ``rotation``, ``precision``,
    ``snr_threshold_db``, ``reference_snr_db`` and ``min_confidence`` (below which a
    controller should not move). The rest is the reference as kept per resolution.
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
        reference = as_image(reference, "reference")
        if mask is not None:
            reference = mask_reference(reference, mask)
            rotation = False
        self.shape = reference.shape
        self.rotation = rotation
        self.precision = precision
        self.snr_threshold_db = snr_threshold_db
        self.reference_snr_db = estimate_snr_db(reference)
        lowpass = gaussian_lowpass(self.shape, mask_band) if mask is not None else None
        self._full = FullResolution.of(reference, window, band, lowpass, fft_effort)
        # The whole-pixel search runs on a pair halved by a binomial filter (four times
        # cheaper FFTs, and the filter lifts the SNR); full resolution is needed only
        # for the sub-pixel fit (precision="full"), which needs no inverse FFT.
        self._half = HalfResolution.of(self._full, window, band, mask_band if mask is not None else None)
        self._quarter = QuarterResolution.of(self._half, fft_effort)
        self._log_polar = LogPolarReference.of(self._full, angles, fft_effort) if rotation else None
        self._probes = ProbeReferences.of(self._full, self._half) if rotation else None

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

        Rotation first when on (eq. 9-12, :meth:`.LogPolarReference.angle`), from the
        same spectrum; then the search runs on the halved image turned back by it, theta
        and theta + 180 are told apart by the translation peak, the angle is refined on
        the image itself (:meth:`_refine_rotation`), and the shift is fitted on the frame
        turned back by the refined angle (at full resolution with ``precision="full"``).
        """
        image, statistics = self._check(image)
        mean = float(statistics.mean)
        snr_db = snr_from_statistics(statistics)
        threshold = self.snr_threshold_db
        filtered = threshold is not None and (snr_db < threshold or self.reference_snr_db < threshold)
        if rotation and not self.rotation:
            raise ValueError("this estimator was made without rotation (rotation=False)")
        if self.rotation and rotation is not False:
            return self._estimate_with_rotation(image, mean, snr_db, filtered)
        if self.precision == "full":
            spectrum = self._full.spectrum(image, mean)
            search = self._half.search_full(spectrum)
            shift = self._full.fit(spectrum, search.shift, filtered)
        else:
            search = self._half.search(self._half.spectrum_of(image, mean), self._half.reference_conjugate)
            shift = self._fit_fast(image, mean, search.shift, filtered)
        return _motion(shift, 0.0, False, search, snr_db, filtered)

    def _check(self, image) -> tuple[np.ndarray, FrameStatistics]:
        """The image as contiguous float32 (no copy when it already is) and its statistics."""
        array = np.asarray(image)
        if array.ndim != 2 or array.size == 0 or array.dtype.kind not in "uifb":
            array = as_image(array)  # raises the precise ValueError
        if array.shape != self.shape:
            raise ValueError(f"image is {array.shape[1]} x {array.shape[0]}, the reference is "
                             f"{self.shape[1]} x {self.shape[0]}")
        array = np.ascontiguousarray(array, dtype=np.float32)
        statistics = frame_statistics(array)
        if not statistics.finite:
            raise ValueError("image contains NaN or infinite values")
        return array, statistics

    # -- translation --------------------------------------------------------------
    def _fit_fast(self, image: np.ndarray, mean: float, shift: Shift, filtered: bool) -> Shift:
        """Steps 2 and 3 on the halved pair (``precision="fast"``): the full-resolution
        window moved by whole full-resolution pixels, then halved, so the scene
        weighting matches to within half a pixel."""
        if self._half.factor == 1:
            return self._full.fit(self._full.spectrum(image, mean), shift, filtered)
        spectrum = self._half.apodized_spectrum(image, mean, int(round(shift.dy)), int(round(shift.dx)))
        fit = self._half.fit(spectrum, self._half.fit_reference_conjugate, shift, filtered)
        return Shift(fit.dy, fit.dx)

    # -- rotation, then translation ---------------------------------------------------
    def _estimate_with_rotation(self, image: np.ndarray, mean: float, snr_db: float, filtered: bool) -> Motion:
        spectrum = self._full.spectrum(image, mean)
        small_image = self._half.factor == 1
        angle = self._log_polar.angle(spectrum, small_turns=small_image)
        if small_image:
            return self._estimate_small_with_rotation(image, mean, angle, snr_db, filtered)
        self._probes.load(image)
        turn = self._turn_from(mean, spectrum, angle, filtered)
        if turn.sharpness == 0.0:
            # No top near the log-polar peak: the magnitude spectrum's strongest peak can
            # be the scene's axis-aligned edges or the window's (a turn near 90 degrees
            # read as 0). Its next peaks are tried, each verified on the image.
            for candidate in self._log_polar.candidates(ANGLE_CANDIDATES)[1:]:
                other = self._turn_from(mean, spectrum, candidate, filtered)
                if other.sharpness > 0.0:
                    turn = other
                    break
        return self._fit_turned(image, mean, spectrum, turn, snr_db, filtered)

    def _turn_from(self, mean: float, spectrum: np.ndarray, angle: float, filtered: bool) -> Turn:
        """From a log-polar angle: the search (theta or theta + 180) and the refinement."""
        if abs(angle) <= SMALL_TURN_PROBES * self._probes.step_deg:
            # A turn this small moves no pixel by more than SMALL_TURN_PROBES: the
            # whole-pixel search does not need the frame turned back.
            search, searched = self._half.search_full(spectrum), self._half.cropped
            reference = self._half.cropped_reference_conjugate
        else:
            search, searched = self._half_search(mean, angle)
            reference = self._half.reference_conjugate
        # theta or theta + 180? The magnitude spectrum cannot tell; the translation
        # peak can: compare it with the peak of the image turned by 180 degrees.
        if self._quarter.turned_is_better(searched, reference):
            angle += 180.0 if angle < 0 else -180.0
            search, _ = self._half_search(mean, angle)
        refined = self._refine_rotation(mean, angle, search.shift, filtered)
        return Turn(refined.angle, refined.sharpness, refined.shift, search)

    def _half_search(self, mean: float, angle: float) -> tuple[Search, np.ndarray]:
        """The whole-pixel search on the halved image turned back by ``angle``, and the
        search spectrum (the plan's buffer)."""
        spectrum = self._half.spectrum(self._probes.turned_back(angle), mean)
        return self._half.search(spectrum, self._half.reference_conjugate), spectrum

    def _refine_rotation(self, mean: float, angle: float, shift: Shift, filtered: bool) -> Refined:
        """The angle at which the frame (halved in ``self._probes`` first) correlates
        best with the reference.

        The log-polar estimate (eq. 9-12) reads the magnitude spectrum only: where that
        is nearly isotropic (round particles, a smooth halo, noise) it wanders by
        tenths of a degree, while the image itself still pins the angle down. So the
        halved frame is registered (the band-limited fit of eq. 18-22) against copies of
        the reference turned by whole probes (``ROTATION_PROBE_PX``, made once) around
        the estimate, and the normalized correlation at each best shift is kept; a
        parabola through the best three gives the angle (:func:`probe_top`). Small
        turns (``SMALL_TURN_PROBES``) are fitted as they are; larger ones are first
        turned back by the estimate. When the top is not between the probes, the copy
        one probe further out on the higher side is tried too.
        """
        probes, half = self._probes, self._half
        if abs(angle) <= SMALL_TURN_PROBES * probes.step_deg:
            turned_back, middle, frame = 0.0, int(round(angle / probes.step_deg)), probes.half_image
        else:
            turned_back, middle, frame = angle, 0, probes.turned_back(angle)
        spectrum = half.windowed_spectrum(frame, mean, shift)
        # The unturned reference's fit starts the others (a turn moves the best shift
        # little: by the turn times the distance from the window's centre).
        best = half.fit(spectrum, probes.conjugates[0], shift, filtered, with_correlation=True)
        fits = {0: best}

        def correlation(probe: int) -> float:
            if probe not in fits:
                fits[probe] = half.fit(spectrum, probes.conjugates[probe], best[:2], filtered, with_correlation=True)
            return fits[probe].correlation

        outermost = SMALL_TURN_PROBES + 1
        for _ in range(2):
            if max(correlation(middle - 1), correlation(middle + 1)) <= correlation(middle):
                break
            step = 1 if correlation(middle + 1) > correlation(middle - 1) else -1
            if abs(middle + step) >= outermost:
                break
            middle += step
        top = probe_top(correlation(middle - 1), correlation(middle), correlation(middle + 1))
        if top is None:
            return Refined(angle, 0.0, shift)
        refined = turned_back + (middle + top.offset) * probes.step_deg
        best_shift = Shift(fits[middle].dy, fits[middle].dx)
        if turned_back == 0.0 and abs(refined) > DEROTATE_ABOVE_DEG:
            # The fits were in the frame's own axes; the fit that follows turns it back.
            theta = np.deg2rad(refined)
            y, x = best_shift
            best_shift = Shift(x * np.sin(theta) + y * np.cos(theta), x * np.cos(theta) - y * np.sin(theta))
        return Refined(float(refined), float(top.sharpness), best_shift)

    def _fit_turned(self, image: np.ndarray, mean: float, spectrum: np.ndarray, turn: Turn, snr_db: float,
                    filtered: bool) -> Motion:
        """The final fit of the frame turned back by the refined angle (``spectrum``: the
        frame's own, used as it is below ``DEROTATE_ABOVE_DEG``)."""
        rotation_confidence = confidence_from_sharpness(turn.sharpness)
        if self.precision == "fast":
            # On the halved frame turned back, under the full-resolution window moved by
            # the whole-pixel shift and halved (as the fast fit's reference).
            half_spectrum = self._half.windowed_spectrum(self._probes.turned_back(turn.angle), mean, turn.shift)
            fit = self._half.fit(half_spectrum, self._half.fit_reference_conjugate, turn.shift, filtered)
            return _motion(Shift(fit.dy, fit.dx), turn.angle, True, turn.search, snr_db, filtered,
                           rotation_confidence)
        derotated = abs(turn.angle) > DEROTATE_ABOVE_DEG
        if derotated:
            spectrum = self._full.spectrum(rotate_about_centre(image, -turn.angle, self._full.frame_buffer()), mean)
        return _motion(self._full.fit(spectrum, turn.shift, filtered), turn.angle, derotated, turn.search, snr_db,
                       filtered, rotation_confidence)

    def _estimate_small_with_rotation(self, image: np.ndarray, mean: float, angle: float, snr_db: float,
                                      filtered: bool) -> Motion:
        """Images under 128 pixels a side have no halved pair: the log-polar angle is
        used as it is (not refined), the search and the fit run at full resolution."""
        derotated = abs(angle) > DEROTATE_ABOVE_DEG
        turned = rotate_about_centre(image, -angle, self._full.frame_buffer()) if derotated else image
        spectrum = self._full.spectrum(turned, mean)
        search = self._half.search_full(spectrum)
        if self._quarter.turned_is_better(self._half.cropped, self._half.cropped_reference_conjugate):
            angle += 180.0 if angle < 0 else -180.0
            derotated = True
            spectrum = self._full.spectrum(rotate_about_centre(image, -angle, self._full.frame_buffer()), mean)
            search = self._half.search_full(spectrum)
        return _motion(self._full.fit(spectrum, search.shift, filtered), angle, derotated, search, snr_db, filtered)
