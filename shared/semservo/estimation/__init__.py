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
* :mod:`.plans`: FFT plans, kept as FFTW wisdom;
* :mod:`.resolutions`: the reference as an estimator keeps it, one structure per
  resolution;
* ``_kernels``: the fused per-pixel loops (numba) the steps run on.

:class:`MotionEstimator` (:mod:`.estimator`) composes them: it precomputes everything
that depends only on the reference (window, reference spectrum, log-polar reference,
FFT plans) once, and :meth:`MotionEstimator.estimate` runs the per-frame part. The
tilts need focus sweeps, not single frames: :func:`.tilt.estimate_tilt`.

The package exports what lab scripts use: :class:`MotionEstimator`, :class:`Motion`,
:func:`estimate_snr_db`, :func:`rotate_about_centre` (the turn of this convention),
:func:`mask_reference` and :func:`polygon_mask` (to see a mask reference),
:func:`as_image`, ``MIN_SIZE`` and ``DEFAULT_SNR_THRESHOLD_DB``.

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
the image's correlation peaks in the angle (the refinement on the image, :meth:`MotionEstimator.estimate`), so
a scene whose turns all look alike has its estimate refused rather than guessed.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

# What lab scripts use, and the module each comes from; every step's function stays
# importable from its module (``semservo.estimation.translation.refine_on_band``, ...).
# Loaded on first use (PEP 562), as scikit-image's lazy_loader does: importing one light
# module of this package (a constant of the raster's, the tilts' conventions) must not
# pull in numba and FFTW, a second or two of every service's start.
_EXPORTS = {
    "DEFAULT_SNR_THRESHOLD_DB": "snr", "MIN_SIZE": "common", "Motion": "common", "MotionEstimator": "estimator",
    "as_image": "common", "estimate_snr_db": "snr", "mask_reference": "masks", "polygon_mask": "masks",
    "rotate_about_centre": "rotation",
}
__all__ = sorted(_EXPORTS)

if TYPE_CHECKING:
    from semservo.estimation.common import MIN_SIZE, Motion, as_image
    from semservo.estimation.estimator import MotionEstimator
    from semservo.estimation.masks import mask_reference, polygon_mask
    from semservo.estimation.rotation import rotate_about_centre
    from semservo.estimation.snr import DEFAULT_SNR_THRESHOLD_DB, estimate_snr_db


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
        globals()[name] = value  # once loaded, an ordinary attribute
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
