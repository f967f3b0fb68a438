""":class:`MotionEstimator`: the sections composed. Everything that depends only on the
reference (window, reference spectrum, log-polar reference, turned references, FFT
plans) is computed once; :meth:`MotionEstimator.estimate` runs the per-frame part:
rotation (:mod:`.rotation`), then translation (:mod:`.translation`), with the SNR
monitored (:mod:`.snr`). Sign convention and confidence: :mod:`semservo.estimation`.
"""

from __future__ import annotations

import cv2
import numpy as np
import pyfftw

from semservo import _kernels
from semservo.estimation.common import MIN_SIZE, Motion, apodization_window, as_image
from semservo.estimation.masks import mask_reference
from semservo.estimation.plans import FFTPlans
from semservo.estimation.rotation import (
    ANGLE_CANDIDATES, AngularRefiner, LogPolarGrid, PROBE_INTERPOLATION, ROTATION_PROBE_PX, SMALL_TURN_PROBES,
    TURNED_REFERENCE_DEG, angular_candidates, angular_spectrum, confidence_from_sharpness, highpass_emphasis,
    log_polar_magnitude, rotate_about_centre,
)
from semservo.estimation.snr import (
    DEFAULT_SNR_THRESHOLD_DB, estimate_snr_db, frame_statistics, gaussian_lowpass, gaussian_transfer,
    snr_from_statistics,
)
from semservo.estimation.translation import (
    PSR_EXCLUSION, PhasePlaneBand, centred_shift, confidence_from_psr, crop_spectrum_into, refine_on_band,
)

#: Turns smaller than this are not undone before measuring translation (they are still
#: reported): a rotation about the image centre adds no net shift, and undoing a turn
#: at the rotation estimate's noise floor (0.02-0.03 degree on real frames) costs a
#: resampling (0.4 ms) and adds interpolation. Larger turns are undone: on real frames,
#: skipping a 0.1 degree turn moves the shift by up to 0.06 px, a 0.05 degree turn by
#: about 0.02 px.
DEROTATE_ABOVE_DEG = 0.05
#: How many moved windows (or reference spectra under them), one per whole-pixel shift,
#: an estimator keeps: a servo loop sees few shifts.
MOVED_WINDOWS_KEPT = 64


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
        statistics = frame_statistics(array)
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
        snr_db = snr_from_statistics(statistics)
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
