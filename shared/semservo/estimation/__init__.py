"""Fourier-domain motion estimation between a taught reference and the current SEM image.

Implements section II-A to II-D of Marturi et al., "Image-Guided Nanopositioning Scheme
for SEM": rotation about the beam from the log-polar magnitude spectrum (eq. 9-12),
refined on the image itself, then sub-pixel translation from the normalized cross-power
spectrum (eq. 18-24), with the image SNR monitored (section II-D) and, on request, noisy
frames filtered.

Small pure functions do each step, one module per section of the paper:

* :mod:`.rotation`: rotation about the beam (section II-B-1, eq. 9-12);
* :mod:`.tilt`: the out-of-plane tilts from focus (section II-B-2, eq. 13-17);
* :mod:`.translation`: sub-pixel translation (section II-C, eq. 18-24);
* :mod:`.snr`: image noise (section II-D);
* :mod:`.common`: the result type, input checks, the apodization window (section II-A);
* :mod:`.masks`: mask references (the paper's case 6);
* :mod:`.plans`: FFT plans, kept as FFTW wisdom.

:class:`MotionEstimator` (:mod:`.estimator`) composes them: it precomputes everything
that depends only on the reference (window, reference spectrum, log-polar reference,
FFT plans) once, and :meth:`MotionEstimator.estimate` runs the per-frame part. The
tilts need focus sweeps, not single frames: :func:`.tilt.estimate_tilt`.

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

from semservo.estimation.common import MIN_SIZE, Motion, apodization_window, as_image
from semservo.estimation.estimator import DEROTATE_ABOVE_DEG, MOVED_WINDOWS_KEPT, MotionEstimator
from semservo.estimation.masks import mask_reference, polygon_mask
from semservo.estimation.plans import FFTPlans, wisdom_path
from semservo.estimation.rotation import (
    AngularRefiner, LogPolarGrid, angular_candidates, angular_shift, angular_spectrum, confidence_from_sharpness,
    highpass_emphasis, log_polar_magnitude, rotate_about_centre,
)
from semservo.estimation.snr import (
    DEFAULT_SNR_THRESHOLD_DB, estimate_snr_db, frame_statistics, gaussian_lowpass, gaussian_transfer,
    snr_from_statistics,
)
from semservo.estimation.translation import (
    PSR_EXCLUSION, PhasePlaneBand, centred_shift, confidence_from_psr, crop_spectrum_into, foroosh_subpixel,
    normalized_cross_power, refine_on_band,
)

__all__ = [
    "DEFAULT_SNR_THRESHOLD_DB", "DEROTATE_ABOVE_DEG", "MIN_SIZE", "MOVED_WINDOWS_KEPT", "PSR_EXCLUSION",
    "AngularRefiner", "FFTPlans", "LogPolarGrid", "Motion", "MotionEstimator", "PhasePlaneBand",
    "angular_candidates", "angular_shift", "angular_spectrum", "apodization_window", "as_image", "centred_shift",
    "confidence_from_psr", "confidence_from_sharpness", "crop_spectrum_into", "estimate_snr_db", "foroosh_subpixel",
    "frame_statistics", "gaussian_lowpass", "gaussian_transfer", "highpass_emphasis", "log_polar_magnitude",
    "mask_reference", "normalized_cross_power", "polygon_mask", "refine_on_band", "rotate_about_centre",
    "snr_from_statistics", "wisdom_path",
]
