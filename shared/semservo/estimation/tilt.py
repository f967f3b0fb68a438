"""Out-of-plane tilts from focus (Marturi et al., section II-B-2): depth from focus per
kernel (eq. 13), and the two tilts from a robust plane fit to the kernel depths.

Two ways from the kernel depths to the tilts, both here, compared in ``bench/tilt.py``:

* the paper's (eq. 14-17): the depths as a point cloud, each kernel's surface normal, the
  extended Gaussian image (EGI: the normals' area-weighted density on the sphere), and
  the rotation that best correlates the taught EGI with the current one
  (:func:`egi_tilt_between`);
* a least-squares plane through the kernel depths, robust to kernels whose focus peak is
  wrong, whose two slopes are the two tilts (:func:`estimate_tilt`, the default: see
  the benchmark for why).

Small pure functions on arrays, no hidden state.

Sign convention (a contract)
----------------------------
Image axes as :mod:`semservo.estimation`: x along columns (right), y along rows (down);
z along the beam, away from the lens, so that (x, y, z) is right-handed and a larger z
is a larger working distance. ``alpha_deg`` is the rotation about x and ``beta_deg`` the
rotation about y, by the right-hand rule: with alpha > 0 the lower part of the image is
farther from the lens (depth grows with y: dz/dy = tan alpha); with beta > 0 the right
part is nearer (dz/dx = -tan beta / cos alpha). The surface's orientation is
R = R_x(alpha) R_y(beta): the sample tilted by beta, then the cradle by alpha, as the
simulated stage (:mod:`semservo.simulation.goniometer`) composes them; seen
orthographically its depth is z = tan(alpha) y - tan(beta) x / cos(alpha), which is the
exact inverse used here (alpha = atan(dz/dy), beta = -atan(cos(alpha) dz/dx)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import NamedTuple, Sequence

import numpy as np


#: A kernel whose focus curve peaks by less than this factor over its lowest value has
#: no clear peak (flat content, or a kernel out of focus over the whole sweep): on a
#: featureless kernel the measure is pixel noise, whose variance over 1000 pixels
#: wanders by +-5-15 % from frame to frame; texture in and out of focus differs by
#: several times.
MIN_FOCUS_CONTRAST = 1.5
#: Fewer usable kernels than this and no plane is fitted.
MIN_KERNELS = 6
#: Kernels whose depth is off the fitted plane by more than this many robust standard
#: deviations (1.4826 x the median absolute residual) are left out and the plane refitted.
OUTLIER_SIGMAS = 3.0
#: A kernel's focus peak is clear only if it stands this many standard errors of its
#: noise-free measure (see :func:`noise_free_focus_curves`) above the lowest value of its
#: curve: a kernel of flat content (the inside of a hole, a dark ground) has a curve of
#: noise whose highest value, over 21 frames, stands 4-5 standard errors above its
#: lowest; one of texture, tens to thousands.
CLEAR_PEAK_SIGMAS = 8.0
#: Tukey's biweight constant for the robust plane fit (95 % efficiency under Gaussian
#: residuals), in robust standard deviations.
BIWEIGHT = 4.685
#: The largest standard error of either tilt (degrees, the jackknife over the kernels,
#: :func:`jackknife_slopes_covariance`) an estimate may have: beyond, the kernels that see focus do
#: not pin the plane (too few, bunched in a corner, or scattered), and it is refused.
MAX_TILT_UNCERTAINTY_DEG = 0.1
#: The largest standard error of either tilt a teach may keep (degrees): a run measures
#: against the taught reading, and both readings' errors together must stay within
#: ``MAX_TILT_UNCERTAINTY_DEG`` (:func:`measured_against`); past an equal share the
#: teach would leave its runs less than it took itself (:func:`as_taught`).
MAX_TAUGHT_UNCERTAINTY_DEG = MAX_TILT_UNCERTAINTY_DEG / math.sqrt(2.0)
#: A kernel's depth is read between the samples of its focus curve (:func:`focus_peaks`);
#: where the curve departs from straight lines between them its centre is pulled by a
#: fraction of a step that depends on where it falls between samples, alike in
#: neighbouring kernels, so the plane's residuals do not show it. The tilts' standard errors are therefore never
#: taken below this fraction of a step over the span of the kernels used (at a depth of
#: field of 14 um the simulator's sweeps, 7 um apart, read tilts 0.4-0.6 degree off with
#: standard errors from the residuals under 0.1; at 3.5 um, 1.75 um apart, this floor is
#: 0.03 degree over a 36 um field). Measured on real textures (``bench/tilt_sampling.py``:
#: noise-free sweeps read as at the tables' dose, the focus anywhere between samples) the
#: pull stays within about twice it under a Gaussian probe, but under a disc blur 0.5-3
#: degrees from the taught pose it reaches 2-4.5 times it (0.06-0.14 degree), and on a
#: few bunched kernels (sparse particles) up to 0.3 degree at any tilt; a run, swept on
#: the taught grid, sheds it as it nears the taught pose.
SAMPLING_BIAS_STEPS = 0.01
#: The largest robust scatter of the kernel depths about the plane, in sweep steps: a
#: scene that is not one plane in focus (or a sweep that blurs it other than by focus).
MAX_SCATTER_STEPS = 0.5
#: Each kernel's depth is the centre of symmetry of its focus curve over the samples
#: within this many steps of it (:func:`focus_peaks`).
SYMMETRY_HALF_WINDOW = 3
#: Candidate centres per sweep step, within a step of the highest sample (then refined
#: by a parabola through the mismatch).
SYMMETRY_CANDIDATES_PER_STEP = 20
#: The fitted reading of a focus curve's centre (:func:`fitted_centres`): 1 / measure as
#: a polynomial of this degree in the distance from the centre (the width squared of a
#: texture blurred by a spot whose width adds to the probe's linearly, a Gaussian's cusp,
#: or in quadrature, the disc of a beam's cone and a round peak, is one of degree 2; the
#: third degree takes up textures of more than one scale), ...
FIT_DEGREE = 3
#: ... over the samples within this many steps of the centre, as many on either side
#: (the flanks of a broad curve, where its noise pins the centre best, lie 5-10 steps out
#: at the sweeps' 1.25 um steps under a disc blur).
FIT_HALF_WINDOW = 8
#: Candidate centres of the fitted reading, within this many steps of the highest sample
#: (a broad, flat-topped peak's highest sample wanders more than one step with the noise),
#: ``SYMMETRY_CANDIDATES_PER_STEP`` per step, then refined by a parabola through the fit's
#: chi-square (at half as many, a cusp's centre was pulled by up to 0.011 step).
FIT_REACH_STEPS = 2
#: The fitted reading uses the samples about the peak whose measure stands this many of
#: its noise's standard deviations above 0 (:func:`fitted_centres`).
FIT_MIN_SNR = 5.0
#: No kernel's depth is trusted to better than this fraction of a sweep step, whatever
#: its focus curve's noise (:func:`focus_peak_uncertainties`): what the noise leaves out
#: (the sampling bias, the content under the kernel) is not weighed away.
DEPTH_UNCERTAINTY_FLOOR_STEPS = 0.02
#: The focus measures a sweep's kernels can be read by (:func:`focus_measure_curves`):
#: ``"normalized_variance"``, the paper's eq. 13 (the default), and ``"gradient"``, each
#: kernel's gradient energy over its mean, which keeps more of what the pixels say about
#: focus on sparse textures (``bench/tilt_bounds.py``).
FOCUS_MEASURES = ("normalized_variance", "gradient")
#: The gradient measure smooths each frame by a Gaussian of this standard deviation (px)
#: before its Sobel gradients: the finest detail is where the pixel noise outweighs what
#: focus changes.
GRADIENT_SMOOTHING_PX = 1.0
#: The most focus sweeps a teach takes of the taught pose (:func:`pooled_tilt`,
#: :func:`wants_another_sweep`): each is 15-25 frames, and pooling n of them narrows the
#: tilts' uncertainty by about 1 / sqrt(n) only while the kernels' depth noise dominates.
MAX_TEACH_SWEEPS = 4

#: Once a view is being pooled, it is swept again while 1 / sqrt(n) projects its
#: standard error within this factor of ``MAX_TILT_UNCERTAINTY_DEG`` (:func:`wants_another_sweep`).
POOLING_SLACK = 1.25

#: The taught pose's tilts are swept again while either is pinned less tightly than this
#: (degrees, its standard error): every later measurement is taken against the taught
#: plane and carries its error whole, so it is pinned tighter than one measurement must
#: be (``MAX_TILT_UNCERTAINTY_DEG``, the line beyond which the teach is refused).
TEACH_UNCERTAINTY_DEG = 0.05


@dataclass(frozen=True)
class TiltEstimate:
    """The two tilts (degrees, see the module's convention), how far the plane is (the
    working distance of focus at the image centre, in the sweep's unit), and how much
    to trust them."""

    alpha_deg: float
    beta_deg: float
    centre_depth: float
    #: Kernels with a clear focus peak that the plane was fitted to, of all kernels.
    kernels_used: int
    kernels_total: int
    #: RMS distance of the used kernels' depths from the plane (the sweep's unit).
    residual: float
    confidence: float
    #: Why the confidence is 0 (empty when it is not).
    reason: str = ""
    #: The standard errors of the two tilts (degrees): the jackknife over the kernels
    #: (:func:`jackknife_slopes_covariance`), never under the sampling bias's floor
    #: (``SAMPLING_BIAS_STEPS``); NaN when no plane was fitted.
    alpha_uncertainty_deg: float = float("nan")
    beta_uncertainty_deg: float = float("nan")
    #: How many focus sweeps of the same view the depths were pooled from (:func:`pooled_tilt`).
    sweeps: int = 1


def normalized_variance(patch: np.ndarray) -> float:
    """The focus measure of one kernel (eq. 13): (1 / k^2) (1 / mu) sum (I - mu)^2, the
    variance over the mean (0 for a kernel of mean 0 or less)."""
    patch = np.asarray(patch, dtype=np.float64)
    mean = float(patch.mean())
    return float(patch.var() / mean) if mean > 0 else 0.0


def focus_curves(sweep: np.ndarray, kernel: int) -> np.ndarray:
    """Eq. 13 for every k x k kernel of every frame of a focus sweep (frames, rows,
    cols): an array (frames, kernel rows, kernel cols). Edge pixels that do not fill a
    kernel are left out."""
    sweep = np.asarray(sweep)
    frames, rows, cols = sweep.shape
    kernel_rows, kernel_cols = rows // kernel, cols // kernel
    curves = np.empty((frames, kernel_rows, kernel_cols))
    for index in range(frames):  # one frame at a time in float32: a sweep can be large
        frame = np.asarray(sweep[index, :kernel_rows * kernel, :kernel_cols * kernel], dtype=np.float32)
        blocks = frame.reshape(kernel_rows, kernel, kernel_cols, kernel)
        mean = blocks.mean(axis=(1, 3), dtype=np.float64)
        mean_square = np.square(blocks).mean(axis=(1, 3), dtype=np.float64)
        variance = np.maximum(mean_square - mean * mean, 0.0)
        curves[index] = np.where(mean > 0, variance / np.where(mean > 0, mean, 1.0), 0.0)
    return curves


def focus_peaks(curves: np.ndarray, working_distances: np.ndarray, assume_clear: np.ndarray | None = None) -> np.ndarray:
    """Each kernel's depth: the working distance of its focus peak, to a fraction of a
    step (the curve's centre of symmetry, :func:`symmetry_centres`, on evenly spaced
    working distances). NaN where the curve has no clear peak: flat (the peak under
    ``MIN_FOCUS_CONTRAST`` times the lowest value) or highest at either end of the sweep
    (the focus lies outside it). ``assume_clear``: which kernels have a clear peak, when
    the caller has judged that (:func:`clear_focus_peaks`)."""
    working_distances = np.asarray(working_distances, dtype=np.float64)
    frames = curves.shape[0]
    best = np.argmax(curves, axis=0)
    highest = np.take_along_axis(curves, best[np.newaxis], axis=0)[0]
    lowest = curves.min(axis=0)
    inside = (best > 0) & (best < frames - 1)
    clear = inside & (highest > MIN_FOCUS_CONTRAST * np.maximum(lowest, 1e-12)) if assume_clear is None else assume_clear
    # The blur of a point depends only on its distance from focus, whatever the probe's
    # shape (a Gaussian spot, the disc of a beam's cone, the simulator's), so a kernel's
    # curve is symmetric about its depth, and its centre of symmetry needs no model of
    # the curve's shape. The parabola through the reciprocals of three samples (exact
    # for a Gaussian probe whose width adds in quadrature) was pulled towards the
    # highest sample by a cusp-like peak: on sweeps of the simulator's scene and of the
    # FIB-SEM slice and the hole under a Gaussian probe whose width grows linearly
    # (16 poses each), the tilts' mean error fell from 0.055, 0.039 and 0.076 degree to
    # 0.031, 0.024 and 0.067, and the worst from 0.16, 0.44 and 0.57 to 0.08, 0.07 and 0.20.
    centres = symmetry_centres(curves, np.clip(best, 1, frames - 2))
    step = (working_distances[-1] - working_distances[0]) / (frames - 1)
    depths = working_distances[0] + centres * step
    return np.where(clear & np.isfinite(centres), depths, np.nan)


def symmetry_centres(curves: np.ndarray, best: np.ndarray, half_window: int = SYMMETRY_HALF_WINDOW) -> np.ndarray:
    """Each curve's centre of symmetry (a fractional sample index) within a sample of
    ``best`` (its highest sample): where the curve, read as 1 / sqrt (for a texture
    blurred by s the measure goes as 1 / s^2, so this is about the blur's width, close
    to a straight line in the distance from focus on either side), best matches its
    mirror image over the samples within ``half_window`` of the centre (the mirror read
    between samples, linearly). NaN where no pair of samples straddles any candidate.

    ``curves``: frames x ... (positive); ``best``: the shape of one frame's values."""
    frames = curves.shape[0]
    width = 1.0 / np.sqrt(np.maximum(curves, 1e-300)).reshape(frames, -1)
    highest = np.asarray(best).ravel()
    kernels = np.arange(highest.size)
    count = 2 * SYMMETRY_CANDIDATES_PER_STEP + 1
    offsets = np.linspace(-1.0, 1.0, count)[:, None, None]  # candidates x 1 x 1
    lags = np.arange(-half_window - 1, half_window + 2)[None, None, :]  # samples about the highest
    samples = highest[None, :, None] + lags  # 1 x kernels x lags
    mirrored = highest[None, :, None] + 2 * offsets - lags  # candidates x kernels x lags
    valid = ((np.abs(lags - offsets) <= half_window) & (samples >= 0) & (samples <= frames - 1)
             & (mirrored >= 0) & (mirrored <= frames - 1))
    below = np.clip(np.floor(mirrored).astype(np.int64), 0, frames - 2)
    fraction = np.clip(mirrored - below, 0.0, 1.0)
    column = kernels[None, :, None]
    mirror = width[below, column] * (1 - fraction) + width[below + 1, column] * fraction
    here = width[np.clip(samples, 0, frames - 1), column]
    pairs = valid & (np.abs(samples - mirrored) > 1e-9)  # a sample against itself says nothing
    mismatch = np.where(pairs.any(axis=2), np.where(valid, (here - mirror) ** 2, 0.0).sum(axis=2)
                        / np.maximum(valid.sum(axis=2), 1), np.inf)  # candidates x kernels
    chosen = np.argmin(mismatch, axis=0)
    inner = np.clip(chosen, 1, count - 2)
    left, middle, right = (mismatch[inner + shift, kernels] for shift in (-1, 0, 1))
    with np.errstate(invalid="ignore"):
        curvature = left - 2 * middle + right
        refine = np.where(np.isfinite(curvature) & (curvature > 0) & (chosen == inner),
                          0.5 * (left - right) / np.where(curvature > 0, curvature, 1.0), 0.0)
    spacing = 2.0 / (count - 1)
    centres = highest + offsets[chosen, 0, 0] + np.clip(refine, -0.5, 0.5) * spacing
    centres = np.where(np.isfinite(mismatch[chosen, kernels]), centres, np.nan)
    return centres.reshape(np.shape(best))


class FocusCurves(NamedTuple):
    """Eq. 13's measure per kernel and frame split into the scene's part and the pixel
    noise's (each a variance over the kernel's mean; frames x kernel rows x kernel cols),
    and the pixels per kernel."""

    signal: np.ndarray
    noise: np.ndarray
    pixels: int


def noise_free_focus_curves(sweep: np.ndarray, kernel: int) -> FocusCurves:
    """Eq. 13 for every k x k kernel of every frame, with the pixel noise's share taken
    out. The kernel's autocovariance at lags 1 and 2 (along rows and columns) holds the
    scene only (pixel noise is uncorrelated from pixel to pixel), so the noise's share
    of R(0) is what lies beyond their extrapolation to lag 0, (4 R(1) - R(2)) / 3 (the
    split of :func:`semservo.estimation.estimate_snr_db`). That split counts detail
    sharp at the pixel scale as noise, and shot noise does not change with focus (it
    goes with the kernel's mean): so each kernel's noise share is the median of its
    split over the sweep, and the scene's is the rest of R(0), over the mean.

    Why: shot noise adds to eq. 13's variance over the mean a floor that does not
    change with focus (for Poisson noise the same in every kernel), which flattens the
    focus curve of a faint texture, pulls its peak fit, and lets kernels of flat content
    (noise only) show a "peak" of noise: on real images (a hole, a dark ground with a
    few particles) those had depths microns off. With the floor removed, the curve of a
    texture blurred by s goes as 1 / s^2, and a kernel of noise only is near 0 at every
    working distance."""
    sweep = np.asarray(sweep)
    frames, rows, cols = sweep.shape
    kernel_rows, kernel_cols = rows // kernel, cols // kernel
    # Imported here: the controller imports this module for the tilts' conventions
    # (foreshortening), and numba is a second of its start.
    from semservo.estimation import _kernels

    statistics = np.empty((frames, kernel_rows, kernel_cols, 4))
    for index in range(frames):  # one frame at a time in float32: a sweep can be large
        frame = np.ascontiguousarray(sweep[index], dtype=np.float32)
        _kernels.kernel_autocovariances(frame, kernel, statistics[index])
    mean, zero_lag, lag1, lag2 = np.moveaxis(statistics, -1, 0)
    scene = (4 * lag1 - lag2) / 3
    positive = mean > 0
    safe_mean = np.where(positive, mean, 1.0)
    noise = np.where(positive, np.maximum(zero_lag - scene, 0.0) / safe_mean, 0.0)
    # The split is exact for a scene smooth at the pixel scale (out of focus) but counts
    # detail sharp at the pixel scale (in focus) as noise. The noise's share does not
    # change with focus (shot noise goes with the kernel's mean, which focus keeps), so
    # each kernel's is its median over the sweep, and the scene's is the rest of R(0).
    floor = np.median(noise, axis=0)
    signal = np.where(positive, zero_lag / safe_mean, 0.0) - floor
    return FocusCurves(signal, np.broadcast_to(floor, noise.shape), kernel * kernel)


@lru_cache(maxsize=8)
def gradient_noise_constants(kernel: int, smoothing_px: float = GRADIENT_SMOOTHING_PX) -> tuple[float, float]:
    """What pixel noise does to the gradient measure (:func:`gradient_focus_curves`), from
    the filters' impulse responses h_x, h_y (a Gaussian of ``smoothing_px``, then Sobel):
    ``gain``, the mean gradient energy of unit white noise, C_xx(0) + C_yy(0) (C the
    responses' cross-correlations), and ``correlation``, how many times more a kernel's
    mean energy scatters than if its pixels' energies were independent,
    sum over lags of (C_xx^2 + C_yy^2 + 2 C_xy^2) / gain^2: the measure then scatters as
    eq. 13's from pixels / correlation pixels. Each lag (dx, dy) counts as often as a
    ``kernel`` x ``kernel`` block holds it, (1 - |dx| / k)(1 - |dy| / k)."""
    import cv2

    side = 2 * int(np.ceil(5 * smoothing_px)) + 9
    impulse = np.zeros((side, side), np.float64)
    impulse[side // 2, side // 2] = 1.0
    smooth = cv2.GaussianBlur(impulse, (0, 0), smoothing_px)
    responses = [cv2.Sobel(smooth, cv2.CV_64F, 1, 0), cv2.Sobel(smooth, cv2.CV_64F, 0, 1)]

    def correlation(first: np.ndarray, second: np.ndarray) -> np.ndarray:
        shape = (2 * side, 2 * side)
        return np.fft.irfft2(np.fft.rfft2(first, shape) * np.conj(np.fft.rfft2(second, shape)), shape)

    xx, yy, xy = (correlation(*pair) for pair in ((responses[0], responses[0]), (responses[1], responses[1]),
                                                  (responses[0], responses[1])))
    gain = float(xx[0, 0] + yy[0, 0])
    lags = np.abs(np.fft.fftfreq(2 * side) * 2 * side)
    pairs = np.clip(1 - lags / kernel, 0.0, None)
    return gain, float(np.sum(np.outer(pairs, pairs) * (xx**2 + yy**2 + 2 * xy**2)) / gain**2)


def gradient_energy(frame: np.ndarray, kernel: int, smoothing_px: float = GRADIENT_SMOOTHING_PX) -> np.ndarray:
    """The gradient measure of one frame, per whole ``kernel`` x ``kernel`` block (kernel
    rows x cols): the mean of |grad(G * I)|^2 over the block (G a Gaussian of
    ``smoothing_px``, the gradient by Sobel) over the block's mean, as eq. 13 divides its
    variance (0 for a block of mean 0 or less)."""
    import cv2

    frame = np.asarray(frame, dtype=np.float32)
    kernel_rows, kernel_cols = frame.shape[0] // kernel, frame.shape[1] // kernel
    smooth = cv2.GaussianBlur(frame, (0, 0), smoothing_px)
    energy = cv2.Sobel(smooth, cv2.CV_32F, 1, 0) ** 2 + cv2.Sobel(smooth, cv2.CV_32F, 0, 1) ** 2
    window = (slice(0, kernel_rows * kernel), slice(0, kernel_cols * kernel))
    blocks = (kernel_rows, kernel, kernel_cols, kernel)
    mean = frame[window].reshape(blocks).mean(axis=(1, 3), dtype=np.float64)
    return np.where(mean > 0, energy[window].reshape(blocks).mean(axis=(1, 3), dtype=np.float64)
                    / np.where(mean > 0, mean, 1.0), 0.0)


def gradient_focus_curves(sweep: np.ndarray, kernel: int, normalized_variance: FocusCurves | None = None,
                          smoothing_px: float = GRADIENT_SMOOTHING_PX) -> FocusCurves:
    """The gradient measure (:func:`gradient_energy`) for every k x k kernel of every
    frame, with the pixel noise's share taken out. The noise's share is eq. 13's
    (``normalized_variance``, from :func:`noise_free_focus_curves`: the pixel noise's
    variance over the mean) times the filters' gain, and the curves say they come from
    pixels / correlation pixels
    (:func:`gradient_noise_constants`), so that every reading of a focus curve (the
    clear-peak test, the mirror, the fitted curve and their standard errors) reads them
    as it reads eq. 13's.

    Why: eq. 13's variance weighs every spatial frequency alike, the coarse ones that focus
    barely changes included; on sparse particles on a dark ground (the drift pair) its
    Cramer-Rao bound is 1.8-2.3 times the pixels' and the gradient energy's 1.1-1.4
    (``bench/tilt_bounds.py``)."""
    sweep = np.asarray(sweep)
    if normalized_variance is None:
        normalized_variance = noise_free_focus_curves(sweep, kernel)
    gain, correlation = gradient_noise_constants(kernel, smoothing_px)
    # One frame at a time in float32: a sweep can be large.
    measure = np.stack([gradient_energy(frame, kernel, smoothing_px) for frame in sweep])
    noise = gain * np.asarray(normalized_variance.noise)
    return FocusCurves(measure - noise, noise, max(1, int(round(kernel * kernel / correlation))))


def _curves_and_eq13(sweep: np.ndarray, kernel: int, measure: str,
                     normalized_variance: FocusCurves | None = None) -> tuple[FocusCurves, FocusCurves]:
    """The noise-free focus curves of ``measure`` and eq. 13's (the same, for eq. 13;
    ``normalized_variance``: eq. 13's of the same sweep, when already made)."""
    if measure not in FOCUS_MEASURES:
        raise ValueError(f"unknown focus measure {measure!r} (one of {', '.join(FOCUS_MEASURES)})")
    if normalized_variance is None:
        normalized_variance = noise_free_focus_curves(sweep, kernel)
    if measure == "normalized_variance":
        return normalized_variance, normalized_variance
    return gradient_focus_curves(sweep, kernel, normalized_variance), normalized_variance


def focus_measure_curves(sweep: np.ndarray, kernel: int, measure: str = "normalized_variance",
                         normalized_variance: FocusCurves | None = None) -> FocusCurves:
    """The noise-free focus curves of ``measure`` (one of ``FOCUS_MEASURES``):
    :func:`noise_free_focus_curves` (eq. 13) or :func:`gradient_focus_curves`
    (``normalized_variance``: eq. 13's of the same sweep, when already made)."""
    return _curves_and_eq13(sweep, kernel, measure, normalized_variance)[0]


def clear_focus_peaks(curves: FocusCurves, working_distances: np.ndarray) -> np.ndarray:
    """Each kernel's depth from its noise-free focus curve (:func:`noise_free_focus_curves`):
    the working distance of its peak, to a fraction of a step (its centre of symmetry, as
    :func:`focus_peaks`). NaN where the peak is not clear: at either end
    of the sweep, not ``MIN_FOCUS_CONTRAST`` times the curve's lowest value, or not
    ``CLEAR_PEAK_SIGMAS`` standard errors above it (the standard error of the scene's
    variance estimated from ``pixels`` noisy pixels, about the noise's variance over the
    square root of their number, or the curve's own scatter, :func:`focus_curve_scatter`,
    whichever is larger)."""
    signal = curves.signal
    frames = signal.shape[0]
    best = np.argmax(signal, axis=0)
    highest = np.take_along_axis(signal, best[np.newaxis], axis=0)[0]
    lowest = signal.min(axis=0)
    noise_at_peak = np.take_along_axis(curves.noise, best[np.newaxis], axis=0)[0]
    standard_error = np.maximum(noise_at_peak / np.sqrt(curves.pixels), focus_curve_scatter(signal))
    inside = (best > 0) & (best < frames - 1)
    clear = (inside & (highest > MIN_FOCUS_CONTRAST * np.maximum(lowest, 0.0))
             & (highest - lowest > CLEAR_PEAK_SIGMAS * standard_error) & (highest > 0))
    floor = 1e-6 * np.maximum(highest, 1e-300)
    return focus_peaks(np.maximum(signal, floor), working_distances, assume_clear=clear)


def focus_curve_scatter(signal: np.ndarray) -> np.ndarray:
    """Each focus curve's frame-to-frame scatter, measured on the curve itself (frames x
    ...): the robust standard deviation of its second differences over the sweep, over
    sqrt(6) (a second difference of independent samples of standard deviation s has
    standard deviation sqrt(6) s). The median leaves out most of the curve's bend about
    its peak (a peak 180 times the noise over its tails reads 1.6 times the noise:
    harmless, the clear-peak test asks for 8). 0 for sweeps too short for most of their
    second differences to lie beyond the peak's ``SYMMETRY_HALF_WINDOW`` (under
    ``4 * SYMMETRY_HALF_WINDOW + 1`` frames, 13: a tracking sweep near flat has 7).

    Why measured, not only modelled: the standard error eq. 13's measure would have from
    pixel noise alone (the noise's share over the square root of the pixels) leaves out
    the scene's part in the variance's scatter and the noise of the kernel's mean; the
    measured scatter is larger on most kernels (a median 1.6 times on the drift pair,
    4-8 times on the grid, the FIB-SEM slice and the hole, there partly the curve's own
    bend in its tails, which a clear peak stands hundreds of times above). On sparse
    particles on a dark ground (the drift pair, 1000 electrons per grey level, a
    Gaussian probe) a quarter of the kernels that passed the clear-peak test on the
    modelled error alone had depths 0.3-13 um off, and pulled the tilts by tenths of a
    degree; with the measured scatter, 6 %."""
    frames = signal.shape[0]
    if frames < 4 * SYMMETRY_HALF_WINDOW + 1:
        return np.zeros(signal.shape[1:])
    second = signal[:-2] - 2 * signal[1:-1] + signal[2:]
    return 1.4826 * np.median(np.abs(second - np.median(second, axis=0)), axis=0) / np.sqrt(6.0)


def focus_peak_uncertainties(curves: FocusCurves, working_distances: np.ndarray) -> np.ndarray:
    """Each kernel's depth's standard error (the sweep's unit, kernel rows x cols), as its
    focus curve's noise carries into its centre of symmetry (:func:`symmetry_centres`),
    never under ``DEPTH_UNCERTAINTY_FLOOR_STEPS`` of a step.

    The centre is read off the curve's width, 1 / sqrt(measure), on the samples within
    ``SYMMETRY_HALF_WINDOW`` of its peak, all weighed alike; moving the centre by d
    changes each mirrored pair's mismatch by the width's growth per step, g, times 2 d,
    so with m samples whose widths scatter by s_w (their RMS) the centre scatters by
    s_w / (g sqrt(m)) steps (g the least-squares slope of the width on the distance from
    the highest sample). The measure's scatter at each sample is that of the scene's
    variance from ``pixels`` noisy pixels, (2 N^2 + 4 S N) / pixels for a scene's share S
    and the noise's N (both over the mean), and carries into the width as s / (2 S^1.5).

    Why: the kernels that see focus differ in how well they pin it by a factor of ten
    (on sparse particles, a bright cluster against a faint one at its edge; on
    drift_pair_before under a Gaussian probe, 44 kernels, 10 sweeps: 0.015-0.16 um). The
    plane weighs each by the inverse square (:func:`robust_plane`), and pooled sweeps
    add them so (:func:`pool_depths`). On 8 sweeps of the flat view, the logs of this
    error and of each kernel's scatter over the sweeps correlate by 0.80-0.88
    (drift_pair_before under both probes, the aperture, the grid under the disc) and
    it reads 1.0-1.6 times the scatter (median); with the curve's measured scatter
    (:func:`focus_curve_scatter`, which the clear-peak test adds) in s it read 1.4-2.4
    times, and 17 times on a clean synthetic texture, where the measured scatter is the
    peak's bend. Only the ratios weigh the plane: :func:`with_excess_scatter` scales
    them to the plane's residuals, and the tilts' standard errors stay the jackknife's."""
    signal = curves.signal
    frames = signal.shape[0]
    working_distances = np.asarray(working_distances, dtype=np.float64)
    step = (working_distances[-1] - working_distances[0]) / (frames - 1)
    floor = DEPTH_UNCERTAINTY_FLOOR_STEPS * step
    half = min(SYMMETRY_HALF_WINDOW, (frames - 1) // 2)
    if half < 1:
        return np.full(signal.shape[1:], floor)
    best = np.clip(np.argmax(signal, axis=0), half, frames - 1 - half)
    highest = np.take_along_axis(signal, best[np.newaxis], axis=0)[0]
    # As clear_focus_peaks reads the curve: a measure at or under 0 (noise only) is a
    # millionth of the peak, a width a thousand times the peak's.
    measure = np.maximum(signal, 1e-6 * np.maximum(highest, 1e-300))

    def at(lag: int) -> np.ndarray:
        return np.take_along_axis(measure, (best + lag)[np.newaxis], axis=0)[0]

    noise = curves.noise[0]
    lags = [lag for lag in range(-half, half + 1) if lag != 0]
    distance = np.abs(np.arange(-half, half + 1, dtype=np.float64))
    distance -= distance.mean()
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        # The width's growth per step: the least-squares slope of the width on the
        # distance from the highest sample, over the whole window (two samples alone
        # would make the weights as noisy as the depths).
        widths = np.stack([at(lag) ** -0.5 for lag in range(-half, half + 1)])
        growth = np.tensordot(distance, widths, axes=1) / np.square(distance).sum()
        width_errors = [0.5 * at(lag) ** -1.5 * np.sqrt((2 * noise**2 + 4 * at(lag) * noise) / curves.pixels)
                        for lag in lags]
        width_error = np.sqrt(np.mean(np.square(width_errors), axis=0))
        uncertainty = step * width_error / (growth * np.sqrt(len(lags)))
    # A curve that does not grow away from its peak, or whose noise overflows, pins
    # nothing: the sweep's whole span.
    sane = np.isfinite(uncertainty) & (growth > 0)
    return np.where(sane, np.clip(uncertainty, floor, step * (frames - 1)), step * (frames - 1))


class KernelDepths(NamedTuple):
    """A sweep's kernel depths (the sweep's unit; NaN where a kernel has no clear focus
    peak) and each one's standard error (:func:`focus_peak_uncertainties`), kernel rows
    x cols: what :func:`kernel_depths` reads and :func:`pool_depths` pools."""

    depths: np.ndarray
    uncertainties: np.ndarray


def fitted_centres(curves: FocusCurves, half_window: int = FIT_HALF_WINDOW,
                   degree: int = FIT_DEGREE) -> tuple[np.ndarray, np.ndarray]:
    """Each kernel's focus peak read by fitting a curve symmetric about it: the centre (a
    fractional sample index) and its standard error (samples), kernel rows x cols; NaN
    and infinite where the fit cannot tell.

    For each candidate centre z (``FIT_REACH_STEPS`` either side of the highest sample),
    1 / measure is fitted by weighted least squares with a polynomial of ``degree`` in
    |d - z| (d the sample's index) over the samples within ``half_window`` of z, as many
    on either side as the sweep has on its shorter one (samples on one side only would
    let the model's misfit pull the centre), the outermost half step faded in so that
    the fit's chi-square is continuous in z. Each sample weighs by its noise: the
    measure's variance from ``pixels`` noisy pixels, (2 N^2 + 4 S N) / pixels as in
    :func:`focus_peak_uncertainties`, carried into 1 / measure as 1 / S^4 (so the tails,
    where the measure nears the noise, weigh little). The centre is the chi-square's
    minimum, refined by a parabola; its standard error sqrt(2 / chi-square's curvature),
    times the square root of the chi-square per degree of freedom where the curve fits
    worse than its noise.

    Why: :func:`symmetry_centres` reads three samples either side of the peak, all
    weighed alike. Where the curve is broad (a disc blur: a texture's variance falls only
    once the blur outgrows its particles, full widths at half maximum of 15-18 um at a
    2.5 um depth of field), those samples sit on the flat top, and the flanks that pin
    the centre are left out: on drift_pair_before's flat view under the disc, 8 sweeps,
    the kernels' depths scattered 0.082 um (median) read so and 0.046 um fitted, 1.06-1.15
    times what the noise allows each kernel (its Cramer-Rao bound). Where too few samples
    stand over the noise (a faint cusp) the fit cannot tell and the mirror's reading
    stands: :func:`focus_peak_depths` keeps, per kernel, the more precise of the two."""
    signal = curves.signal
    frames = signal.shape[0]
    flat = signal.reshape(frames, -1)
    noise = np.asarray(curves.noise[0], dtype=np.float64).reshape(-1)
    kernels = flat.shape[1]
    nan_shape = signal.shape[1:]
    terms = degree + 1
    if frames < terms + 2 or kernels == 0:
        return np.full(nan_shape, np.nan), np.full(nan_shape, np.inf)
    columns = np.arange(kernels)
    best = np.clip(np.argmax(flat, axis=0), 1, frames - 2)
    highest = flat[best, columns]
    scale = np.where(highest > 0, highest, 1.0)
    # Each curve over its highest value (the fit does not depend on the measure's scale),
    # floored as clear_focus_peaks floors it: a measure at or under 0 is a millionth.
    measure = np.maximum(flat / scale, 1e-6)  # frames x kernels

    def variance_of_reciprocal(model: np.ndarray) -> np.ndarray:
        # The measure's noise at the measure ``model`` (over the highest value), carried
        # into 1 / measure.
        variance = (2 * noise**2 + 4 * np.maximum(model * scale, 0.0) * noise) / curves.pixels / scale**2
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            return np.clip(np.nan_to_num(variance / np.maximum(model, 1e-6) ** 4, nan=1e30), 1e-30, 1e30)

    # Only the samples around the peak whose measure stands FIT_MIN_SNR of its noise
    # over 0, as many on either side: beyond, 1 / measure is too skewed by the noise for
    # its linearised variance to weigh it (a faint texture read 5 times its modelled
    # error off when its tails were fitted).
    noise_of_measure = np.sqrt((2 * noise**2 + 4 * np.maximum(flat, 0.0) * noise) / curves.pixels)
    stands = flat >= FIT_MIN_SNR * noise_of_measure

    def run_length(direction: int) -> np.ndarray:
        """How many samples in a row from the highest one, that way, stand."""
        index = best[None, :] + direction * np.arange(1, frames)[:, None]
        ok = (index >= 0) & (index < frames) & np.take_along_axis(stands, np.clip(index, 0, frames - 1), axis=0)
        return np.argmin(np.vstack([ok, np.zeros((1, kernels), dtype=bool)]), axis=0)

    half = np.minimum(np.minimum(run_length(-1), run_length(+1)), half_window).astype(np.float64)

    count = 2 * SYMMETRY_CANDIDATES_PER_STEP * FIT_REACH_STEPS + 1
    offsets = np.linspace(-FIT_REACH_STEPS, FIT_REACH_STEPS, count)
    spacing = offsets[1] - offsets[0]
    # Every sample by its lag from the kernel's highest one: the design (the powers of
    # |lag - offset|) is then the same for every kernel, and the normal equations of all
    # kernels at a candidate are one matrix product.
    longest = min(frames - 1, half_window + FIT_REACH_STEPS + 1)  # no window reaches further
    lags = np.arange(-longest, longest + 1)
    samples = best[:, None] + lags[None, :]  # kernels x lags
    inside = (samples >= 0) & (samples < frames)
    samples = np.clip(samples, 0, frames - 1)
    distance = np.abs(lags[None, :] - offsets[:, None])  # candidates x lags
    design = distance[..., None] ** np.arange(terms)  # candidates x lags x terms
    products = (design[..., :, None] * design[..., None, :]).reshape(count, len(lags), terms * terms)
    centres = best[None, :] + offsets[:, None]  # candidates x kernels
    reach = np.minimum(np.minimum(centres, frames - 1 - centres), half[None, :])
    window = np.clip(reach[:, :, None] + 0.5 - distance[:, None, :], 0.0, 1.0) * inside[None]  # c x k x lags
    target = np.take_along_axis(1.0 / measure.T, samples, axis=1)  # kernels x lags
    degrees_of_freedom = np.maximum(window.sum(axis=-1) - terms - 1, 1.0)
    usable = np.count_nonzero(window > 0, axis=-1) >= terms + 2

    def fit(sample_variance: np.ndarray, candidates: slice = slice(None)):
        """The ``candidates``' fits with these variances of 1 / measure (frames x
        kernels): the chi-square (candidates x kernels) and the coefficients."""
        weights = window[candidates] / np.take_along_axis(sample_variance.T, samples, axis=1)[None]
        normal = np.matmul(weights, products[candidates]).reshape(len(weights), kernels, terms, terms)
        moments = np.matmul(weights * target[None], design[candidates])  # candidates x kernels x terms
        good = usable[candidates] & np.isfinite(normal).all(axis=(-1, -2))
        normal = np.where(good[..., None, None], normal, np.eye(terms))
        # Scaled to a unit diagonal: the powers of |d - z| span orders over 8 steps.
        diagonal = np.sqrt(np.maximum(np.einsum("ckii->cki", normal), 1e-300))
        scaled = normal / (diagonal[..., :, None] * diagonal[..., None, :])
        coefficients = np.linalg.solve(scaled + 1e-12 * np.eye(terms), (moments / diagonal)[..., None])[..., 0] \
            / diagonal
        # At the least-squares coefficients, chi-square = y'Wy - c'X'Wy.
        chi_square = np.sum(weights * target[None] ** 2, axis=-1) - np.sum(coefficients * moments, axis=-1)
        return np.where(good, np.maximum(chi_square, 0.0), np.inf), coefficients

    # Twice: first weighed by the measured curve, then by the curve the first fit found
    # (a sample that the noise raised would otherwise weigh more for it). The first
    # only needs a rough centre for that: every fourth candidate.
    coarse = slice(None, None, 4)
    chi_square, coefficients = fit(variance_of_reciprocal(measure), coarse)
    first = np.argmin(chi_square, axis=0)
    design_first = design[coarse][first]
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        at_lags = 1.0 / np.einsum("klt,kt->kl", design_first, coefficients[first, columns])
    modelled = measure.copy()
    rows = np.broadcast_to(samples, at_lags.shape)[inside]
    kernel_of = np.broadcast_to(columns[:, None], at_lags.shape)[inside]
    values = at_lags[inside]
    modelled[rows, kernel_of] = np.where(np.isfinite(values) & (values > 0), values, measure[rows, kernel_of])
    chi_square, _ = fit(variance_of_reciprocal(modelled))

    chosen = np.argmin(chi_square, axis=0)
    inner = np.clip(chosen, 1, count - 2)
    left, middle, right = (chi_square[inner + shift, columns] for shift in (-1, 0, 1))
    with np.errstate(invalid="ignore", over="ignore"):
        curvature = left - 2 * middle + right
        interior = np.isfinite(curvature) & (curvature > 0) & (chosen == inner)
        refine = np.where(interior, 0.5 * (left - right) / np.where(interior, curvature, 1.0), 0.0)
        centre = best + offsets[chosen] + np.clip(refine, -0.5, 0.5) * spacing
        misfit = np.maximum(1.0, middle / degrees_of_freedom[inner, columns])
        error = np.sqrt(2.0 * spacing**2 / np.where(interior, curvature, np.nan) * misfit)
    # A minimum at the candidates' edge, or no fit at all: the fit cannot tell.
    told = interior & np.isfinite(error) & (highest > 0)
    return (np.where(told, centre, np.nan).reshape(nan_shape), np.where(told, error, np.inf).reshape(nan_shape))


def focus_peak_depths(curves: FocusCurves, working_distances: np.ndarray) -> KernelDepths:
    """Each kernel's depth (NaN where its peak is not clear, :func:`clear_focus_peaks`)
    and its standard error, the more precise of two readings of its focus curve's centre:
    the mirror (:func:`symmetry_centres`, :func:`focus_peak_uncertainties`), which needs no
    model of the curve and reads a cusp-like peak well, and the fit of a symmetric curve
    (:func:`fitted_centres`), which reads a broad peak from its flanks.

    Why both: on drift_pair_before under the disc (flat view, 8 sweeps) the fit read the
    kernels' depths nearly twice as precisely (0.046 against 0.082 um, median scatter) and the
    tilts' standard errors fell from 0.24-0.39 to 0.15-0.24 degree; under the Gaussian
    probe the two scattered alike (0.032 um) and either one alone did worse on some
    texture (``bench/tilt_real.py``). Each reading's standard error comes from the same
    noise model, so the choice is by which the noise pins better, not by which reads
    closer to the others."""
    working_distances = np.asarray(working_distances, dtype=np.float64)
    frames = curves.signal.shape[0]
    step = (working_distances[-1] - working_distances[0]) / (frames - 1)
    mirrored = clear_focus_peaks(curves, working_distances)
    mirrored_errors = focus_peak_uncertainties(curves, working_distances)
    # Only the kernels with a clear peak are fitted (a sparse texture's are a fifth).
    clear = np.isfinite(mirrored)
    centres = np.full(mirrored.shape, np.nan)
    errors = np.full(mirrored.shape, np.inf)
    if clear.any():
        centres[clear], errors[clear] = fitted_centres(
            FocusCurves(curves.signal[:, clear], np.asarray(curves.noise)[:, clear], curves.pixels))
    fitted = working_distances[0] + centres * step
    fitted_errors = np.clip(errors * step, DEPTH_UNCERTAINTY_FLOOR_STEPS * step, None)
    use_fit = np.isfinite(mirrored) & np.isfinite(fitted) & (fitted_errors < mirrored_errors)
    depths = np.where(use_fit, fitted, mirrored)
    return KernelDepths(depths, np.where(np.isfinite(depths), np.where(use_fit, fitted_errors, mirrored_errors),
                                         np.nan))


def kernel_centres(shape: tuple[int, int], kernel: int, pixel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """The kernels' centres (y, x: each kernel rows x cols) relative to the image's centre,
    in the sweep's unit (``pixel_size`` per pixel): where the plane reads each depth."""
    kernel_rows, kernel_cols = shape
    y = ((np.arange(kernel_rows) + 0.5) * kernel - kernel_rows * kernel / 2) * pixel_size
    x = ((np.arange(kernel_cols) + 0.5) * kernel - kernel_cols * kernel / 2) * pixel_size
    return np.meshgrid(y, x, indexing="ij")


class PlaneFit(NamedTuple):
    """A robust plane through the kernel depths (:func:`robust_plane`): depth = c + gx x +
    gy y, the kernels' final weights (0: left out), the residuals' robust standard
    deviation in depth (the median over every kernel's residual; with uncertainties,
    over the kernels kept), and the coefficients' covariance."""

    coefficients: np.ndarray
    weights: np.ndarray
    scale: float
    covariance: np.ndarray

    @property
    def tilts_deg(self) -> tuple[float, float]:
        """The plane's alpha, beta (degrees) in the module's convention: alpha =
        atan(gy), beta = -atan(cos(alpha) gx)."""
        _, slope_x, slope_y = self.coefficients
        return (float(np.degrees(np.arctan(slope_y))),
                float(np.degrees(np.arctan(-slope_x * np.cos(np.arctan(slope_y))))))


def robust_plane(depths: np.ndarray, kernel: int, pixel_size: float, iterations: int = 30,
                 uncertainties: np.ndarray | None = None) -> PlaneFit:
    """The plane depth = c + gx x + gy y (x, y the kernel centres relative to the image
    centre, in the sweep's unit) through the kernels with a depth, by iteratively
    reweighted least squares with Tukey's biweight (``BIWEIGHT`` robust standard
    deviations, the scale the median absolute residual), started from
    :func:`fit_plane`: kernels whose depth is wrong by microns (a peak of noise, an
    edge that entered the kernel) get no weight, those a little off a little less. The
    covariance is the residual scale squared times (X^T W X)^-1.

    ``uncertainties`` (each depth's standard error, :func:`focus_peak_uncertainties`;
    only their ratios matter): each kernel weighs 1 / uncertainty^2 besides its biweight,
    which then reads its residual in its own standard errors. None: all alike."""
    finite, design, values, errors = _plane_problem(depths, kernel, pixel_size, uncertainties)
    fits = _robust_planes(design, values, errors, np.ones((1, values.size), dtype=bool), iterations)
    coefficients, weights, scale = fits.coefficients[0], fits.weights[0], float(fits.scales[0])
    all_weights = np.zeros(depths.shape)
    all_weights[finite] = weights
    used = weights > 0
    if used.sum() >= 3 and scale > 0:
        normal = (design[used] * weights[used, None]).T @ design[used]
        covariance = scale**2 * np.linalg.pinv(normal)
    else:
        covariance = np.full((3, 3), np.inf)
    if uncertainties is not None and used.any():
        # The scale above is in each kernel's standard errors; the plane's is in depth.
        scale = 1.4826 * float(np.median(np.abs(values - design @ coefficients)[used]))
    return PlaneFit(coefficients, all_weights, scale, covariance)


def _plane_problem(depths: np.ndarray, kernel: int, pixel_size: float, uncertainties: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The kernels with a depth (a mask of ``depths``' shape) and, for them, the plane's
    design (1, x, y at each kernel's centre, :func:`kernel_centres`), their depths and
    their standard errors (``uncertainties``, or ones)."""
    grid_y, grid_x = kernel_centres(depths.shape, kernel, pixel_size)
    finite = np.isfinite(depths)
    design = np.column_stack([np.ones(finite.sum()), grid_x[finite], grid_y[finite]])
    errors = (np.ones(design.shape[0]) if uncertainties is None
              else np.asarray(uncertainties, dtype=np.float64)[finite])
    return finite, design, depths[finite], errors


class _Planes(NamedTuple):
    coefficients: np.ndarray  # problems x 3
    weights: np.ndarray  # problems x kernels (0: left out)
    scales: np.ndarray  # problems: the last robust scale, in each kernel's standard errors


def _weighted_planes(design: np.ndarray, values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted least-squares planes, one per row of ``weights`` (problems x kernels):
    the normal equations solved, through their pseudo-inverse where they are singular
    (the least-norm answer, as ``lstsq`` gives)."""
    # As matrix products (kernels' outer products flattened): einsum's three operands were
    # half the jackknife's time.
    outer = (design[:, :, None] * design[:, None, :]).reshape(len(design), 9)
    normal = (weights @ outer).reshape(-1, 3, 3)
    moments = weights @ (design * values[:, None])
    try:
        return np.linalg.solve(normal, moments[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return np.einsum("pij,pj->pi", np.linalg.pinv(normal), moments)


def _masked_medians(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Each row's median over its entries in ``mask`` (a row with none: NaN)."""
    if values.shape[1] == 0:
        return np.full(values.shape[0], np.nan)
    ordered = np.sort(np.where(mask, values, np.inf), axis=1)
    count = mask.sum(axis=1)
    rows = np.arange(len(count))
    lower, upper = np.maximum(count - 1, 0) // 2, np.maximum(count, 1) // 2
    with np.errstate(invalid="ignore"):
        return np.where(count > 0, 0.5 * (ordered[rows, lower] + ordered[rows, upper]), np.nan)


def _least_squares_planes(design: np.ndarray, values: np.ndarray, included: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`fit_plane` for each row of ``included`` (problems x kernels: which kernels
    each plane is fitted to): the least-squares plane, refitted once without the kernels
    off it by more than ``OUTLIER_SIGMAS`` robust standard deviations. Returns the
    coefficients (problems x 3) and the kernels used (problems x kernels)."""
    problems = included.shape[0]
    used = included.copy()
    coefficients = np.zeros((problems, 3))
    going = np.ones(problems, dtype=bool)
    for _ in range(2):
        going &= used.sum(axis=1) >= 3
        rows = np.flatnonzero(going)
        if rows.size == 0:
            break
        coefficients[rows] = _weighted_planes(design, values, used[rows].astype(np.float64))
        residuals = np.abs(values[None, :] - coefficients[rows] @ design.T)
        spread = 1.4826 * _masked_medians(residuals, used[rows])
        keep = used[rows] & (residuals <= OUTLIER_SIGMAS * np.maximum(spread, 1e-12)[:, None])
        changed = keep.sum(axis=1) != used[rows].sum(axis=1)
        used[rows[changed]] = keep[changed]
        going[rows[~changed]] = False
    return coefficients, used


def _robust_planes(design: np.ndarray, values: np.ndarray, errors: np.ndarray, included: np.ndarray,
                   iterations: int = 30) -> _Planes:
    """:func:`robust_plane`'s iteratively reweighted least squares for each row of
    ``included`` (problems x kernels: which kernels each plane is fitted to), all at
    once: ``design`` (kernels x 3: 1, x, y), ``values`` (the depths) and ``errors``
    (their standard errors, or ones) of every kernel with a depth. One problem is
    :func:`robust_plane`; one per kernel left out is the jackknife's
    (:func:`jackknife_slopes_covariance`), a refit per kernel at the cost of a few."""
    problems = included.shape[0]
    prior = np.where(included, 1.0 / np.square(errors)[None, :], 0.0)
    coefficients, _ = _least_squares_planes(design, values, included)
    weights = prior.copy()
    scales = np.zeros(problems)
    tolerance = 1e-9 * np.maximum(1.0, np.max(np.where(included, np.abs(values)[None, :], 0.0), axis=1, initial=0.0))
    going = np.ones(problems, dtype=bool)
    for _ in range(iterations):
        rows = np.flatnonzero(going)
        if rows.size == 0:
            break
        residuals = (values[None, :] - coefficients[rows] @ design.T) / errors[None, :]
        # The scale from every kernel's residual, not only those still weighed: with
        # uneven weights a few precise kernels fit closely, and a scale of those alone
        # shrinks round by round until it leaves out good kernels (a corner of 9 kernels
        # kept 5). The median holds against the wrong ones as long as they are a minority.
        scale = 1.4826 * _masked_medians(np.abs(residuals), included[rows])
        scales[rows] = scale
        flat = ~(scale > 0)
        going[rows[flat]] = False
        rows, residuals, scale = rows[~flat], residuals[~flat], scale[~flat]
        u = residuals / (BIWEIGHT * scale[:, None])
        weighed = np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0) * prior[rows]
        weights[rows] = weighed
        few = (weighed > 0).sum(axis=1) < 3
        going[rows[few]] = False
        rows, weighed = rows[~few], weighed[~few]
        if rows.size == 0:
            continue
        updated = _weighted_planes(design, values, weighed)
        settled = np.all(np.abs(updated - coefficients[rows]) <= tolerance[rows, None], axis=1)
        coefficients[rows] = updated
        going[rows[settled]] = False
    return _Planes(coefficients, weights, scales)


def with_excess_scatter(depths: np.ndarray, uncertainties: np.ndarray, kernel: int, pixel_size: float,
                        rounds: int = 2) -> np.ndarray:
    """Each kernel's uncertainty with the scatter about the plane that its focus curve's
    noise does not explain added in quadrature, and the whole scaled to that scatter:
    sqrt(a (uncertainty^2 + excess^2)), one excess and one scale a for all kernels, by
    maximum likelihood (the kernels' residuals about the robust plane, those it keeps, as
    normal with that variance; a profiled out, the excess searched over 0 and 0.05-50
    times the median uncertainty on a log grid), the plane refitted with them ``rounds``
    times, starting from every kernel alike. The result is in depth, the standard errors
    the residuals bear out: sweeps pooled (:func:`pool_depths`) weigh each other by them.

    Why: the focus curve's noise is not every error in a kernel's depth. A rough surface,
    content that enters a kernel, the sampling between steps scatter the depths alike
    whatever the noise; weighed by the noise alone, the few quiet kernels would decide the
    plane and its standard errors would grow (a plane +-0.3 um rough over a 64 um field:
    0.114 degree, over the 0.1 line the unweighed fit stays under). Where the noise
    explains the scatter (sparse particles) the excess is 0 and the weights stand; where
    it explains none of it (a faint synthetic texture) they even out."""
    uncertainties = np.asarray(uncertainties, dtype=np.float64)
    finite = np.isfinite(depths) & np.isfinite(uncertainties)
    if finite.sum() < MIN_KERNELS:
        return uncertainties
    typical = float(np.median(uncertainties[finite]))
    candidates = np.concatenate([[0.0], typical * np.logspace(np.log10(0.05), np.log10(50.0), 31)])
    effective = np.where(finite, 1.0, np.nan)  # first round: all alike (the unweighed plane)
    grid_y, grid_x = kernel_centres(depths.shape, kernel, pixel_size)
    for _ in range(rounds):
        plane = robust_plane(depths, kernel, pixel_size, uncertainties=effective)
        kept = finite & (plane.weights > 0)
        if kept.sum() < MIN_KERNELS:
            break
        centre, slope_x, slope_y = plane.coefficients
        squared = (depths - (centre + slope_x * grid_x + slope_y * grid_y))[kept] ** 2
        variances = uncertainties[kept][None, :] ** 2 + candidates[:, None] ** 2
        level = np.mean(squared[None, :] / variances, axis=1)
        with np.errstate(divide="ignore"):
            likelihood = -np.sum(np.log(level[:, None] * variances), axis=1)
        best = int(np.argmax(np.where(np.isfinite(likelihood), likelihood, -np.inf)))
        if not level[best] > 0:
            break
        effective = np.sqrt(level[best] * (uncertainties**2 + candidates[best] ** 2))
    return effective


def jackknife_slopes_covariance(depths: np.ndarray, kernel: int, pixel_size: float,
                                uncertainties: np.ndarray | None = None) -> np.ndarray:
    """The covariance (2 x 2: x then y) of the robust plane's slopes (:func:`robust_plane`)
    by the jackknife over kernels: the plane fitted again without each kernel with a
    depth in turn, (n - 1) / n times the sum of the slopes' squared deviations from
    their mean (Efron and Stein 1981). Infinite with fewer than ``MIN_KERNELS`` depths.

    Why not the residuals' scale times (X^T W X)^-1: that assumes every kernel's depth
    is as noisy as the typical one (the median's scale sees the many precise ones), and
    a robust fit on a few dozen kernels is not linear in them (one kernel more or less
    reweights the rest). On sparse particles the kernels that see focus differ in how
    well they pin it (the edges of a textured band are fainter). Over single sweeps of
    8 random poses, 2 noise draws each (``bench/tilt_real.py``'s textures and noise,
    both defocus models), the tilts' errors had an RMS of 1.1-1.8 standard errors
    from the residuals and 0.85-1.2 from the jackknife on the drift pair, and 0.8-1.7
    and 0.8-1.45 on the grid, the FIB-SEM slice, the aperture and the hole (the
    aperture under the disc the highest either way). Its cost: a refit per kernel,
    all fitted at once (:func:`_robust_planes`). ``uncertainties``: as :func:`robust_plane` weighs them."""
    _, design, values, errors = _plane_problem(depths, kernel, pixel_size, uncertainties)
    count = len(values)
    if count < MIN_KERNELS:
        return np.full((2, 2), np.inf)
    # Every refit at once, each without one kernel (one row of the identity's complement).
    slopes = _robust_planes(design, values, errors, ~np.eye(count, dtype=bool)).coefficients[:, 1:]
    deviations = slopes - slopes.mean(axis=0)
    return (count - 1) / count * (deviations.T @ deviations)


def fit_plane(depths: np.ndarray, kernel: int, pixel_size: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares plane depth = c + gx x + gy y through the kernels with a depth (x, y
    the kernel centres relative to the image centre, in the sweep's unit via
    ``pixel_size``), refitted once without the kernels off it by more than
    ``OUTLIER_SIGMAS`` robust standard deviations. Returns ((c, gx, gy), the mask of
    kernels used, RMS residual)."""
    finite, design, values, _ = _plane_problem(depths, kernel, pixel_size)
    coefficients, kept = _least_squares_planes(design, values, np.ones((1, values.size), dtype=bool))
    coefficients = coefficients[0]
    used = np.zeros(depths.shape, dtype=bool)
    used[finite] = kept[0]
    residuals = values[kept[0]] - design[kept[0]] @ coefficients
    rms = float(np.sqrt(np.mean(residuals**2))) if kept[0].any() else float("nan")
    return coefficients, used, rms


def check_sweep(sweep, working_distances, pixel_size: float, kernel: int = 32) -> None:
    """ValueError, saying what is wrong, for input that cannot be a focus sweep: under 3
    frames, a length mismatch, unevenly spaced or non-finite distances, non-finite pixels,
    a pixel size that is not a positive number, kernels that do not fit."""
    sweep = np.asarray(sweep)
    working_distances = np.asarray(working_distances, dtype=np.float64)
    if sweep.ndim != 3 or sweep.dtype.kind not in "uif":
        raise ValueError(f"a focus sweep is frames x rows x cols of numbers, got shape {sweep.shape} of {sweep.dtype}")
    if sweep.shape[0] < 3:
        raise ValueError(f"a focus sweep needs at least 3 frames to find a peak, got {sweep.shape[0]}")
    if working_distances.shape != (sweep.shape[0],):
        raise ValueError(f"{sweep.shape[0]} frames but {working_distances.size} working distances")
    steps = np.diff(working_distances)
    if not np.isfinite(working_distances).all() or (steps <= 0).any() or np.ptp(steps) > 1e-6 * abs(steps.mean()):
        raise ValueError("working distances must be finite, increasing and evenly spaced")
    if not np.isfinite(sweep).all():
        raise ValueError("the sweep contains NaN or infinite pixels")
    if not (np.isfinite(pixel_size) and pixel_size > 0):
        raise ValueError(f"pixel_size must be a positive number, got {pixel_size!r}")
    if kernel < 4 or min(sweep.shape[1:]) < 2 * kernel:
        raise ValueError(f"{kernel} px kernels do not fit a {sweep.shape[2]} x {sweep.shape[1]} image twice")


def estimate_tilt(sweep, working_distances, pixel_size: float, kernel: int = 32,
                  content_shifts_px=None, measure: str = "normalized_variance") -> TiltEstimate:
    """The two tilts from a focus sweep: frames of the same field at the working
    distances ``working_distances`` (evenly spaced, increasing, same unit as
    ``pixel_size``: e.g. um and um per pixel). ``content_shifts_px``: how far each
    frame's content had moved while the sweep scanned (:func:`depth_map`); ``measure``:
    the focus measure (``FOCUS_MEASURES``, :func:`kernel_depths`).

    ValueError for input that cannot be a sweep (:func:`check_sweep`). A sweep that
    cannot tell the tilts (too few kernels with a clear focus peak: a flat, featureless
    scene, or a sweep that misses focus) gives confidence 0 and the reason, never a
    made-up angle (the angles are NaN).
    """
    check_sweep(sweep, working_distances, pixel_size, kernel)
    working_distances = np.asarray(working_distances, dtype=np.float64)
    depths = kernel_depths(sweep, working_distances, kernel, pixel_size, content_shifts_px, measure)
    return tilt_from_depths(depths.depths, kernel, pixel_size, float(np.diff(working_distances).mean()),
                            depths.uncertainties)


def texture_offsets(sweep: np.ndarray, curves: FocusCurves, kernel: int,
                    half_window: int = SYMMETRY_HALF_WINDOW) -> np.ndarray:
    """Where in each kernel its focus peak comes from: the offset (rows, cols: kernel
    rows x kernel cols x 2, pixels from the kernel's centre) of the centroid of each
    pixel's share of the peak, (I - mu)^2 in the kernel's sharpest frame less its mean
    over the frames ``half_window`` steps either side (the span over which the peak's
    centre is read, :func:`symmetry_centres`; the pixel noise's share is alike in all
    and cancels), kept where positive. 0 where no pixel stands out.

    Why: a kernel's focus curve is the sum of its pixels' curves, each symmetric about
    its own point's depth, so its centre is the depth where its texture lies, not at the
    kernel's centre. Over a texture of sparse particles or bands, the texture at the
    edge of a textured region lies towards its inside: with the depths placed at the
    kernel centres, the plane is squeezed and the tilts read small (on the drift pair
    under a Gaussian probe, 32 px kernels, (3, 3) degrees read 0.3 degree small with
    standard errors of 0.08 after 8 sweeps pooled: a bias of the texture, not the noise,
    that pooling does not narrow)."""
    sweep = np.asarray(sweep)
    signal = curves.signal
    frames, kernel_rows, kernel_cols = signal.shape
    best = np.argmax(signal, axis=0)
    floor = curves.noise[0]  # the noise's share (a variance over the mean), alike in every frame
    offsets = np.zeros((kernel_rows, kernel_cols, 2))
    position = np.arange(kernel) - (kernel - 1) / 2

    # The sweep in kernels, in its own type: only the kernels read below become float64.
    frame_blocks = sweep[:, :kernel_rows * kernel, :kernel_cols * kernel] \
        .reshape(frames, kernel_rows, kernel, kernel_cols, kernel)

    def blocks(index: int, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The chosen kernels' pixels in one frame (n x k x k) and their squared deviations
        from each kernel's mean: only the kernels whose peak that frame is, so each
        kernel is read in three frames, not every frame in full."""
        frame = frame_blocks[index, rows, :, cols, :].astype(np.float64)
        return np.square(frame - frame.mean(axis=(1, 2), keepdims=True)), frame

    for index in np.unique(best):
        rows, cols = np.nonzero(best == index)
        sharp, frame = blocks(int(index), rows, cols)
        far = [blocks(other, rows, cols)[0] for other in (index - half_window, index + half_window)
               if 0 <= other < frames]
        # Without a frame on either side (a sweep of under half_window + 1 frames), the
        # noise's share is taken out as its expected value, floor x mean, per pixel.
        share = np.maximum(sharp - (np.mean(far, axis=0) if far
                                    else floor[rows, cols, None, None] * np.maximum(frame, 0.0)), 0.0)
        total = share.sum(axis=(1, 2))
        stands_out = total > 0
        safe = np.where(stands_out, total, 1.0)
        offsets[rows, cols, 0] = np.where(stands_out, (share.sum(axis=2) @ position) / safe, 0.0)
        offsets[rows, cols, 1] = np.where(stands_out, (share.sum(axis=1) @ position) / safe, 0.0)
    return offsets


def depths_at_kernel_centres(depths: np.ndarray, offsets: np.ndarray, kernel: int, pixel_size: float,
                             iterations: int = 2, uncertainties: np.ndarray | None = None) -> np.ndarray:
    """The kernel depths (read where each kernel's texture lies, ``offsets`` from
    :func:`texture_offsets`) moved to the kernels' centres along the plane through them
    (:func:`robust_plane`, refitted on the moved depths ``iterations`` times): depth -
    (gx dx + gy dy). Unchanged where fewer than ``MIN_KERNELS`` have a depth (no plane to
    move them along). The plane's slopes are known far better than the move needs (a
    degree off moves a depth by 1.7 % of an offset of at most half a kernel).
    ``uncertainties``: as :func:`robust_plane` weighs them."""
    depths = np.asarray(depths, dtype=np.float64)
    if np.isfinite(depths).sum() < MIN_KERNELS:
        return depths
    moved = depths
    for _ in range(iterations):
        _, slope_x, slope_y = robust_plane(moved, kernel, pixel_size, uncertainties=uncertainties).coefficients
        if not np.isfinite([slope_x, slope_y]).all():
            return depths
        moved = depths - (slope_x * offsets[..., 1] + slope_y * offsets[..., 0]) * pixel_size
    return moved


def tilt_from_depths(depths: np.ndarray, kernel: int, pixel_size: float, step: float,
                     uncertainties: np.ndarray | None = None) -> TiltEstimate:
    """The two tilts from the kernel depths (NaN: no clear peak): a robust plane
    (:func:`robust_plane`, each kernel weighed by its ``uncertainties`` when given), or a
    refusal with the reason where the depths cannot pin it:

    * too few kernels with a clear peak (``MIN_KERNELS``), or that the plane holds for;
    * either tilt's standard error above ``MAX_TILT_UNCERTAINTY_DEG``: the kernels that
      see focus are too few, bunched in part of the field, or scattered (the reason
      says how much of the field they span);
    * the depths scatter about the plane by more than ``MAX_SCATTER_STEPS`` sweep steps
      (``step``): not one plane in focus.
    """
    total = depths.size
    clear = int(np.isfinite(depths).sum())
    nan = float("nan")
    if clear < MIN_KERNELS:
        return TiltEstimate(nan, nan, nan, clear, total, nan, 0.0,
                            f"only {clear} of {total} kernels have a clear focus peak (at least {MIN_KERNELS} "
                            "are needed): flat content, or focus outside the sweep")
    if uncertainties is not None:
        # Again, though kernel_depths scaled each sweep's: pooled sweeps share what the
        # sampling and the content put in every sweep alike, which pooling does not narrow.
        uncertainties = with_excess_scatter(depths, uncertainties, kernel, pixel_size)
    plane = robust_plane(depths, kernel, pixel_size, uncertainties=uncertainties)
    centre, slope_x, slope_y = plane.coefficients
    used = plane.weights > 0
    alpha, beta = plane.tilts_deg
    # Standard errors: d alpha = d gy / (1 + gy^2); d beta ~ cos(alpha) d gx / (1 + cos^2 gx^2).
    cos_alpha = np.cos(np.arctan(slope_y))
    rows, cols = np.nonzero(used)
    span_y = (np.ptp(rows) + 1) * kernel * pixel_size if rows.size else np.inf
    span_x = (np.ptp(cols) + 1) * kernel * pixel_size if cols.size else np.inf
    slopes_spread = jackknife_slopes_covariance(depths, kernel, pixel_size, uncertainties)
    slope_y_error = np.hypot(np.sqrt(slopes_spread[1, 1]), SAMPLING_BIAS_STEPS * step / span_y)
    slope_x_error = np.hypot(np.sqrt(slopes_spread[0, 0]), SAMPLING_BIAS_STEPS * step / span_x)
    alpha_error = float(np.degrees(slope_y_error / (1 + slope_y**2)))
    beta_error = float(np.degrees(slope_x_error * cos_alpha / (1 + (cos_alpha * slope_x) ** 2)))
    estimate = TiltEstimate(alpha, beta, float(centre), int(used.sum()), total, plane.scale,
                            float(np.exp(-plane.scale / step)) if np.isfinite(plane.scale) else 0.0, "",
                            alpha_error, beta_error)

    def refused(reason: str) -> TiltEstimate:
        return TiltEstimate(nan, nan, estimate.centre_depth, estimate.kernels_used, total, estimate.residual, 0.0,
                            reason, alpha_error, beta_error)

    if used.sum() < MIN_KERNELS:
        return refused(f"the plane holds for only {int(used.sum())} of the {clear} kernels with a clear focus peak "
                       f"(at least {MIN_KERNELS} are needed)")
    if max(alpha_error, beta_error) > MAX_TILT_UNCERTAINTY_DEG:
        span_x, span_y = (np.ptp(cols) + 1) / depths.shape[1], (np.ptp(rows) + 1) / depths.shape[0]
        pinned = (f"the {int(used.sum())} kernels that see focus (of {total}, spanning {span_x:.0%} x {span_y:.0%} of "
                  f"the field) pin the tilts to +-{alpha_error:.2f} and +-{beta_error:.2f} degree only (at most "
                  f"{MAX_TILT_UNCERTAINTY_DEG:g})")
        if min(span_x, span_y) < 0.5:
            return refused(f"{pinned}: too few or bunched in part of the field, their depths scattered by "
                           f"{plane.scale / step:.2f} sweep steps")
        # Spread over the field: each kernel's focus is placed too loosely against the
        # depth a tenth of a degree spans across the field.
        field_depth = float(np.radians(MAX_TILT_UNCERTAINTY_DEG) * min(span_x * depths.shape[1],
                                                                       span_y * depths.shape[0]) * kernel * pixel_size)
        return refused(f"{pinned}: their depths scatter by {plane.scale:.3g} ({plane.scale / step:.2f} sweep steps) "
                       f"about the plane, where a tenth of a degree spans {field_depth:.2g} across the field. A depth "
                       f"of field too large for the tilts to show across this field (a larger aperture or a shorter "
                       f"working distance makes it smaller), too few kernels, or a surface that is not flat")
    if plane.scale > MAX_SCATTER_STEPS * step:
        return refused(f"the kernel depths scatter about the plane by {plane.scale / step:.2f} sweep steps (at most "
                       f"{MAX_SCATTER_STEPS:g}): the scene is not one plane in focus")
    return estimate


# --------------------------------------------------------------------------------------
# The taught pose, swept more than once


def pool_depths(depth_maps: Sequence[KernelDepths | np.ndarray]) -> KernelDepths:
    """The kernel depths of several focus sweeps of one view pooled (:func:`kernel_depths`'
    maps, NaN where a kernel has no clear peak): each kernel's mean over the sweeps where
    it has a depth, each sweep's weighed by the inverse square of its uncertainty, and
    the pooled uncertainty 1 / sqrt(sum of those weights); NaN where it has a depth in
    fewer than half of them (a peak seen once in four sweeps is a marginal one). A plain
    array of depths weighs alike in every kernel (uncertainty 1).

    Why the depths and not the focus curves: the noise in a kernel's depth is the pixel
    noise of its sweep, independent from sweep to sweep, so the mean of n depths
    scatters about the plane 1 / sqrt(n) as much and the plane's standard errors
    (:func:`tilt_from_depths`) fall with it, down to the floor of
    ``SAMPLING_BIAS_STEPS`` (sweeps on the same working distances share that bias);
    averaging the noise-free focus curves instead did as well on real textures
    (``bench/tilt_real.py``) but needs the same working distances in every sweep."""
    maps = [depths if isinstance(depths, KernelDepths)
            else KernelDepths(np.asarray(depths, dtype=np.float64), np.ones(np.shape(depths)))
            for depths in depth_maps]
    if (not maps or maps[0].depths.ndim != 2
            or any(depths.depths.shape != maps[0].depths.shape or depths.uncertainties.shape != maps[0].depths.shape
                   for depths in maps)):
        raise ValueError("pool_depths needs one or more depth maps (kernel rows x cols) of the same shape")
    depths = np.stack([np.asarray(each.depths, dtype=np.float64) for each in maps])
    uncertainties = np.stack([np.asarray(each.uncertainties, dtype=np.float64) for each in maps])
    seen = np.isfinite(depths) & np.isfinite(uncertainties) & (uncertainties > 0)
    count = seen.sum(axis=0)
    weights = np.where(seen, 1.0 / np.where(seen, uncertainties, 1.0) ** 2, 0.0)
    total = weights.sum(axis=0)
    enough = (count >= np.ceil(len(maps) / 2)) & (count > 0)
    safe_total = np.where(enough, total, 1.0)
    mean = (weights * np.where(seen, depths, 0.0)).sum(axis=0) / safe_total
    return KernelDepths(np.where(enough, mean, np.nan), np.where(enough, 1.0 / np.sqrt(safe_total), np.nan))


def pooled_tilt(depth_maps: Sequence[KernelDepths | np.ndarray], kernel: int, pixel_size: float,
                step: float) -> TiltEstimate:
    """The tilts from the pooled depths of one or more sweeps of the same view
    (:func:`pool_depths`, :func:`tilt_from_depths` weighing each kernel by its pooled
    uncertainty), with ``sweeps`` set; a refusal's reason says how many sweeps were pooled."""
    pooled = pool_depths(depth_maps)
    estimate = replace(tilt_from_depths(pooled.depths, kernel, pixel_size, step, pooled.uncertainties),
                       sweeps=len(depth_maps))
    if estimate.reason and len(depth_maps) > 1:
        estimate = replace(estimate, reason=f"after {len(depth_maps)} sweeps pooled, {estimate.reason}")
    return estimate


def wants_another_sweep(estimate: TiltEstimate, max_sweeps: int = MAX_TEACH_SWEEPS,
                        line_deg: float = MAX_TILT_UNCERTAINTY_DEG, begun: bool = False) -> bool:
    """Whether a teach should sweep the same view once more and pool it
    (:func:`pooled_tilt`): while fewer than ``max_sweeps`` are taken, when either tilt's
    standard error is above ``TEACH_UNCERTAINTY_DEG`` (or the estimate is over
    ``line_deg``: ``MAX_TILT_UNCERTAINTY_DEG`` for a single estimate,
    ``MAX_TAUGHT_UNCERTAINTY_DEG`` for a teach, what :func:`line_against` leaves for a
    measurement against the taught plane), and pooling
    ``max_sweeps`` could bring a refused estimate under the line at the best rate,
    1 / sqrt(n): a texture hopeless at that rate after its first sweep is refused at once
    (the estimate's reason stands), not swept again; once pooling has begun, the
    projection may be up to ``POOLING_SLACK`` over the line (``begun``: it has, in sweeps
    before these, the wide ones a teach's fine sweeps follow). An estimate refused for
    another reason (too few kernels with a clear peak, depths that are not one plane) is
    not swept again either."""
    if estimate.sweeps >= max_sweeps:
        return False
    worst = max(estimate.alpha_uncertainty_deg, estimate.beta_uncertainty_deg)
    if not np.isfinite(worst):
        return False
    over = worst > line_deg
    if estimate.confidence > 0 and not over:
        return worst > TEACH_UNCERTAINTY_DEG
    if not over or estimate.kernels_used < MIN_KERNELS:
        return False  # refused for another reason than its uncertainty
    best_reachable = worst * np.sqrt(estimate.sweeps / max_sweeps)
    if estimate.sweeps > 1 or begun:
        # Once pooling has begun, a projection a little over the line is not a verdict:
        # the pooled standard error is itself estimated, from a few dozen kernels'
        # residuals, and pooling is not exactly 1 / sqrt(n) (a teach of the aperture read
        # +-0.12 after 3 sweeps, projecting 0.104 for 4, and was refused where another
        # teach's 4 sweeps had read +-0.09).
        return best_reachable <= POOLING_SLACK * line_deg
    return best_reachable <= line_deg


def as_taught(estimate: TiltEstimate) -> TiltEstimate:
    """``estimate`` (a teach's, pooled) refused (confidence 0, NaN angles, the reason)
    where either tilt's standard error is over ``MAX_TAUGHT_UNCERTAINTY_DEG``: against it
    a run's sweeps would have to be pinned more tightly than the teach itself, which the
    same texture cannot give (:func:`line_against`).

    Why: drift_pair_before taught to +-0.09 after 4 sweeps left its runs +-0.04; every
    sweep of them was refused and each run ended at its iteration limit, 600 iterations
    later, instead of the teach saying at once that this texture cannot pin the tilts."""
    worst = max(estimate.alpha_uncertainty_deg, estimate.beta_uncertainty_deg)
    if estimate.confidence <= 0 or worst <= MAX_TAUGHT_UNCERTAINTY_DEG:
        return estimate
    swept = "1 sweep" if estimate.sweeps == 1 else f"{estimate.sweeps} sweeps pooled"
    nan = float("nan")
    return replace(estimate, alpha_deg=nan, beta_deg=nan, confidence=0.0,
                   reason=(f"after {swept}, the {estimate.kernels_used} kernels that see focus pin the tilts to "
                           f"+-{estimate.alpha_uncertainty_deg:.2f} and +-{estimate.beta_uncertainty_deg:.2f} degree "
                           f"only (a teach may keep at most +-{MAX_TAUGHT_UNCERTAINTY_DEG:.2f}: against it a run's "
                           f"sweeps would have to be pinned to +-{line_against(estimate):.2f}, tighter than the "
                           "teach itself)"))


def line_against(taught: TiltEstimate) -> float:
    """The largest standard error (degrees, either tilt) a measurement may have for its
    tilts against the ``taught`` reading to be within ``MAX_TILT_UNCERTAINTY_DEG``: the
    difference of two readings has both their standard errors, in quadrature. 0 where
    the teach alone takes the whole line."""
    worst = max(taught.alpha_uncertainty_deg, taught.beta_uncertainty_deg)
    if not np.isfinite(worst):
        return 0.0
    return float(np.sqrt(max(MAX_TILT_UNCERTAINTY_DEG**2 - worst**2, 0.0)))


def measured_against(estimate: TiltEstimate, taught: TiltEstimate) -> TiltEstimate:
    """``estimate``, refused (confidence 0, NaN angles, the reason) where its tilts
    against the ``taught`` reading would be pinned to worse than
    ``MAX_TILT_UNCERTAINTY_DEG``: its own standard error over :func:`line_against`.
    Its standard errors stay its own (a run's sweeps share the teach's error, so whether
    one sweep differs from the next is a matter of theirs alone).

    Why: a run servoes onto the taught reading, so what it is left with is the teach's
    error and the last measurement's together. Each gated at 0.1 degree alone, a loose
    teach of sparse particles (+-0.08, 4 sweeps pooled) and a pose pinned to +-0.1 read
    0.33 degree off (drift_pair_before under the disc, ``bench/tilt_real.py``): a wrong
    angle that a run would have acted on."""
    if estimate.confidence <= 0:
        return estimate
    worst = max(estimate.alpha_uncertainty_deg, estimate.beta_uncertainty_deg)
    line = line_against(taught)
    if worst <= line:
        return estimate
    taught_worst = max(taught.alpha_uncertainty_deg, taught.beta_uncertainty_deg)
    nan = float("nan")
    return replace(estimate, alpha_deg=nan, beta_deg=nan, confidence=0.0,
                   reason=(f"against the taught plane (pinned to +-{taught_worst:.2f} degree) the tilts would be pinned "
                           f"to +-{np.hypot(worst, taught_worst):.2f} degree only (at most {MAX_TILT_UNCERTAINTY_DEG:g}): "
                           f"this sweep's +-{worst:.2f} is over the +-{line:.2f} the teach leaves"))


# --------------------------------------------------------------------------------------
# The paper's method: normals, extended Gaussian image, correlation over rotations
# (eq. 14-17)

#: Smoothing of the EGI (von Mises-Fisher concentration): a kernel normal's direction is
#: uncertain by a few degrees (depth noise of ~0.1 step over one kernel's width).
EGI_CONCENTRATION = 300.0
#: The EGI is kept on a grid over the cap of directions within this angle of the beam
#: (gnomonic coordinates tan(angle)): tilts beyond it are outside the stage's use.
EGI_CAP_DEG = 35.0
EGI_GRID = 141


def depth_map(sweep, working_distances, kernel: int = 32, pixel_size: float | None = None,
              content_shifts_px=None, measure: str = "normalized_variance") -> np.ndarray:
    """Each kernel's depth at its centre (NaN where it has no clear focus peak): the
    depths of :func:`kernel_depths`, without their uncertainties."""
    return kernel_depths(sweep, working_distances, kernel, pixel_size, content_shifts_px, measure).depths


def kernel_depths(sweep, working_distances, kernel: int = 32, pixel_size: float | None = None,
                  content_shifts_px=None, measure: str = "normalized_variance") -> KernelDepths:
    """Each kernel's depth at its centre (NaN where it has no clear focus peak) and its
    standard error: eq. 13 without the noise's share and the peak's centre
    (:func:`noise_free_focus_curves`, :func:`focus_peak_depths`), the first step of both
    methods; with
    ``pixel_size`` (the sweep's unit per pixel), each depth is moved from where the
    kernel's texture lies to the kernel's centre (:func:`texture_offsets`,
    :func:`depths_at_kernel_centres`) and the scatter about the plane that the noise does
    not explain is added to the standard errors (:func:`with_excess_scatter`).

    ``content_shifts_px`` (frames x 2: how far each frame's content had moved, right and
    down, from the sweep's middle frame; :func:`content_shifts`): the frames are first
    moved back (:func:`steady_sweep`), and kernels at the border that would be read
    partly from mirrored pixels (:data:`MIRRORED_KERNEL_FRACTION`) are left out.

    ``measure``: the focus measure the curves are read by (``FOCUS_MEASURES``; eq. 13 by
    default, :func:`focus_measure_curves`); where each kernel's texture lies is read off
    eq. 13's curves whichever it is."""
    if content_shifts_px is not None:
        sweep = steady_sweep(sweep, content_shifts_px)
    sweep = np.asarray(sweep)
    curves, normalized_variance = _curves_and_eq13(sweep, kernel, measure)
    left_out = None if content_shifts_px is None else mirrored_kernels(content_shifts_px, sweep.shape[1:], kernel)
    return depths_from_curves(sweep, curves, normalized_variance, working_distances, kernel, pixel_size, left_out)


def depths_from_curves(sweep, curves: FocusCurves, normalized_variance: FocusCurves, working_distances,
                       kernel: int = 32, pixel_size: float | None = None,
                       left_out: np.ndarray | None = None) -> KernelDepths:
    """:func:`kernel_depths`' reading of a sweep's noise-free focus curves: ``curves``, by
    the measure read (:func:`focus_measure_curves`), and ``normalized_variance``, eq. 13's,
    where each kernel's texture lies is read off; ``left_out`` (kernel rows x cols, True
    to leave a kernel out). Apart so that curves made otherwise can be read alike (a
    noise-free sweep read as its noisy twin would be, ``bench/tilt_sampling.py``)."""
    sweep = np.asarray(sweep)
    working_distances = np.asarray(working_distances, dtype=np.float64)
    depths, uncertainties = focus_peak_depths(curves, working_distances)
    if left_out is not None:
        depths = np.where(left_out, np.nan, depths)
    uncertainties = np.where(np.isfinite(depths), uncertainties, np.nan)
    if pixel_size is not None:
        offsets = texture_offsets(sweep, normalized_variance, kernel)
        depths = depths_at_kernel_centres(depths, offsets, kernel, pixel_size,
                                          uncertainties=uncertainties)
        # What the noise does not explain, added here: sweeps pooled then weigh alike
        # what weighs alike (pool_depths).
        uncertainties = with_excess_scatter(depths, uncertainties, kernel, pixel_size)
    return KernelDepths(depths, uncertainties)


# --------------------------------------------------------------------------------------
# A sweep whose content moved while it scanned

#: Of a frame moved back (:func:`steady_sweep`), a kernel that would take more than this
#: fraction of its width or height from the mirrored margin is left out of the depths.
MIRRORED_KERNEL_FRACTION = 0.125
#: The mirrored margin around a frame moved back (:func:`steady_sweep`), beyond its
#: largest move: it fades to the frame's mean over this width.
STEADY_MARGIN_PX = 24


def content_shifts(frame_times, track_times, track_dx_px, track_dy_px) -> np.ndarray | None:
    """How far each frame of a sweep had its content moved (frames x 2: right and down,
    px) from the sweep's middle frame, read off a track of the same view's content
    position over time: the live frames' shifts against the reference, at the middle of
    their scans (``track_*``), interpolated linearly to the middle of each sweep frame's
    scan (``frame_times``, the same clock). None when the track does not cover the sweep
    (fewer than two points, or a frame more than the track's typical spacing before its
    first point or after its last).

    Why: a sweep takes seconds to minutes, and drift (or the stage's x, y moves) carries
    its content across the kernels meanwhile. Texture entering and leaving a kernel
    changes its focus curve in time, which moves its peak: the fake lab's drift of
    2.5 nm/s over a 28 s sweep (1 px) read the hole's tilts 0.08 degree off in the same
    direction in every sweep, which pooling does not narrow. Measured on the live frames
    (sharp, at the nominal focus), the moves are known to a few hundredths of a pixel;
    measured on the sweep's own frames they are not (blurred frames register 0.2-0.45 px
    off). Each live shift is first taken as the median of it and its neighbours', so that
    one wrong estimate is not followed."""
    frame_times = np.asarray(frame_times, dtype=np.float64)
    times, first = np.unique(np.asarray(track_times, dtype=np.float64), return_index=True)
    if frame_times.ndim != 1 or frame_times.size == 0 or times.size < 2 or not np.isfinite(frame_times).all():
        return None
    spacing = float(np.median(np.diff(times)))
    if frame_times.min() < times[0] - spacing or frame_times.max() > times[-1] + spacing:
        return None
    dx = np.interp(frame_times, times, _median_of_three(np.asarray(track_dx_px, dtype=np.float64)[first]))
    dy = np.interp(frame_times, times, _median_of_three(np.asarray(track_dy_px, dtype=np.float64)[first]))
    middle = frame_times.size // 2
    return np.column_stack([dx - dx[middle], dy - dy[middle]])


def _median_of_three(values: np.ndarray) -> np.ndarray:
    """Each value replaced by the median of it and its two neighbours (the ends kept): one
    wrong live estimate (a repeated pattern read a period off) is not followed, while a
    drift or a stage's step is, a frame late at most."""
    if values.size < 3:
        return values
    smoothed = values.copy()
    smoothed[1:-1] = np.median(np.stack([values[:-2], values[1:-1], values[2:]]), axis=0)
    return smoothed


def steady_sweep(sweep, content_shifts_px) -> np.ndarray:
    """The sweep with each frame moved back by its content's move (:func:`content_shifts`),
    as float32: a phase ramp over the frame padded with its mirror image, which moves it
    by fractions of a pixel without smoothing it (interpolation would blur each frame by
    its own fraction, and the focus measure with it). The mirrored margin fades to the
    frame's mean (a raised cosine over ``STEADY_MARGIN_PX`` and the largest move), so
    that the padded frame is continuous where the transform wraps it round and the ramp
    does not ring; the frame's own pixels are not weighted."""
    frames = np.asarray(sweep)
    shifts = np.asarray(content_shifts_px, dtype=np.float64)
    if frames.ndim != 3 or shifts.shape != (frames.shape[0], 2) or not np.isfinite(shifts).all():
        raise ValueError(f"content shifts must be finite, one (dx, dy) per frame: {shifts.shape} for "
                         f"{frames.shape[0] if frames.ndim == 3 else '?'} frames")
    rows, cols = frames.shape[1:]
    if np.abs(shifts).max(initial=0.0) >= min(rows, cols) / 2:
        raise ValueError("content shifts of half the frame or more: not the same view")
    margin = int(np.ceil(np.abs(shifts).max(initial=0.0))) + STEADY_MARGIN_PX
    shape = (_fast_length(rows + 2 * margin), _fast_length(cols + 2 * margin))
    top, left = (shape[0] - rows) // 2, (shape[1] - cols) // 2
    pad = ((top, shape[0] - rows - top), (left, shape[1] - cols - left))
    fade = _fade(shape[0], *pad[0])[:, None] * _fade(shape[1], *pad[1])[None, :]
    along_rows, along_cols = np.fft.fftfreq(shape[0]), np.fft.rfftfreq(shape[1])
    steadied = np.empty(frames.shape, np.float32)
    for index, (frame, (dx, dy)) in enumerate(zip(frames, shifts)):
        if dx == 0 and dy == 0:
            steadied[index] = frame
            continue
        pixels = np.asarray(frame, dtype=np.float32)
        mean = np.float32(pixels.mean())
        padded = mean + fade * (np.pad(pixels, pad, mode="symmetric") - mean)
        # The ramp exp(2 pi i (f_y dy + f_x dx)) as the product of its two separable halves.
        ramp = (np.exp(2j * np.pi * along_rows * dy).astype(np.complex64)[:, None]
                * np.exp(2j * np.pi * along_cols * dx).astype(np.complex64)[None, :])
        moved = np.fft.irfft2(np.fft.rfft2(padded) * ramp, s=shape)
        steadied[index] = moved[top:top + rows, left:left + cols]
    return steadied


def _fast_length(length: int) -> int:
    """The smallest length of at least ``length`` with no prime factor above 5 (quick to
    transform)."""
    best, twos = None, 1
    while twos < 2 * length:
        threes = twos
        while threes < 2 * length:
            fives = threes
            while fives < length:
                fives *= 5
            best = fives if best is None else min(best, fives)
            threes *= 3
        twos *= 2
    return best


def _fade(length: int, before: int, after: int) -> np.ndarray:
    """1 over the frame, a raised cosine down towards 0 over the margins before and after it."""
    weight = np.ones(length, np.float32)
    if before:
        weight[:before] = 0.5 * (1 - np.cos(np.pi * (np.arange(before) + 0.5) / before))
    if after:
        weight[length - after:] = 0.5 * (1 + np.cos(np.pi * (np.arange(after) + 0.5) / after))
    return weight


def mirrored_kernels(content_shifts_px, shape: tuple[int, int], kernel: int) -> np.ndarray:
    """Which kernels (kernel rows x cols) of a sweep moved back by ``content_shifts_px``
    (:func:`steady_sweep`) would take more than ``MIRRORED_KERNEL_FRACTION`` of their
    width or height from the mirrored margin in some frame: content that moved right
    is moved back left, and the frame's right edge is then mirrored pixels."""
    shifts = np.asarray(content_shifts_px, dtype=np.float64)
    rows, cols = shape
    kernel_rows, kernel_cols = rows // kernel, cols // kernel

    def along(length: int, count: int, moves: np.ndarray) -> np.ndarray:
        starts = np.arange(count) * kernel
        low = max(-float(moves.min(initial=0.0)), 0.0)  # content moved up/left: mirrored at the start
        high = max(float(moves.max(initial=0.0)), 0.0)  # moved down/right: mirrored at the end
        from_low = np.clip(low - starts, 0, kernel)
        from_high = np.clip(starts + kernel - (length - high), 0, kernel)
        return np.maximum(from_low, from_high) > MIRRORED_KERNEL_FRACTION * kernel

    return along(rows, kernel_rows, shifts[:, 1])[:, None] | along(cols, kernel_cols, shifts[:, 0])[None, :]


def kernel_normals(depths: np.ndarray, kernel: int, pixel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """The point cloud's surface normals (eq. 14): at each kernel with at least 5 depths in
    its 3 x 3 neighbourhood, a plane fitted to them; the normal points towards the lens,
    (gx, gy, -1) normalised for a local depth z = c + gx x + gy y. Returns (normals N x 3,
    area weights N): a patch's area on the surface is its kernel's over |n_z|."""
    rows, cols = depths.shape
    spacing = kernel * pixel_size
    normals, weights = [], []
    offsets_y, offsets_x = np.mgrid[-1:2, -1:2]
    for row in range(rows):
        for col in range(cols):
            if not np.isfinite(depths[row, col]):
                continue
            window = depths[max(row - 1, 0):row + 2, max(col - 1, 0):col + 2]
            wy = offsets_y[max(1 - row, 0):3 - max(row + 2 - rows, 0), max(1 - col, 0):3 - max(col + 2 - cols, 0)]
            wx = offsets_x[max(1 - row, 0):3 - max(row + 2 - rows, 0), max(1 - col, 0):3 - max(col + 2 - cols, 0)]
            usable = np.isfinite(window)
            if usable.sum() < 5:
                continue
            design = np.column_stack([np.ones(usable.sum()), wx[usable] * spacing, wy[usable] * spacing])
            _, slope_x, slope_y = np.linalg.lstsq(design, window[usable], rcond=None)[0]
            normal = np.array([slope_x, slope_y, -1.0])
            normal /= np.linalg.norm(normal)
            normals.append(normal)
            weights.append(1.0 / abs(normal[2]))
    return np.reshape(normals, (-1, 3)), np.asarray(weights)


def tilt_rotation(alpha_deg: float, beta_deg: float) -> np.ndarray:
    """R = R_x(alpha) R_y(beta), the module's convention."""
    alpha, beta = np.radians(alpha_deg), np.radians(beta_deg)
    about_x = np.array([[1, 0, 0], [0, np.cos(alpha), -np.sin(alpha)], [0, np.sin(alpha), np.cos(alpha)]])
    about_y = np.array([[np.cos(beta), 0, np.sin(beta)], [0, 1, 0], [-np.sin(beta), 0, np.cos(beta)]])
    return about_x @ about_y


def _gnomonic(directions: np.ndarray) -> np.ndarray:
    """Directions near (0, 0, -1) as points (x / -z, y / -z) of the tangent plane."""
    return directions[..., :2] / -directions[..., 2:3]


def extended_gaussian_image(normals: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The EGI (eq. 15): the area-weighted density of the normals over the cap of
    directions near the beam, smoothed by a von Mises-Fisher kernel, on a gnomonic grid
    of ``EGI_GRID`` x ``EGI_GRID`` points over +-tan(``EGI_CAP_DEG``)."""
    reach = np.tan(np.radians(EGI_CAP_DEG))
    axis = np.linspace(-reach, reach, EGI_GRID)
    plane_x, plane_y = np.meshgrid(axis, axis)
    directions = np.stack([plane_x, plane_y, -np.ones_like(plane_x)], axis=-1)
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    density = np.zeros_like(plane_x)
    for normal, weight in zip(normals, weights):
        density += weight * np.exp(EGI_CONCENTRATION * (directions @ normal - 1.0))
    return density


def _egi_at(egi: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """The EGI interpolated (bilinearly on its gnomonic grid) at these directions; 0 off
    the cap or facing away."""
    reach = np.tan(np.radians(EGI_CAP_DEG))
    facing = directions[..., 2] < -1e-6
    plane = _gnomonic(np.where(facing[..., None], directions, np.array([0.0, 0.0, -1.0])))
    position = (plane + reach) / (2 * reach) * (EGI_GRID - 1)
    inside = facing & np.all((position >= 0) & (position <= EGI_GRID - 1), axis=-1)
    position = np.clip(position, 0, EGI_GRID - 1.000001)
    low = np.floor(position).astype(int)
    fraction = position - low
    col, row = low[..., 0], low[..., 1]
    fx, fy = fraction[..., 0], fraction[..., 1]
    value = (egi[row, col] * (1 - fx) * (1 - fy) + egi[row, col + 1] * fx * (1 - fy)
             + egi[row + 1, col] * (1 - fx) * fy + egi[row + 1, col + 1] * fx * fy)
    return np.where(inside, value, 0.0)


def egi_correlation(reference_egi: np.ndarray, normals: np.ndarray, weights: np.ndarray,
                    alpha_deg: np.ndarray, beta_deg: np.ndarray) -> np.ndarray:
    """C(R) = sum_i w_i EGI*(R^T n_i) (eq. 16) for each tilt rotation R(alpha, beta) of the
    arrays given: the current normals turned back by R, scored on the taught EGI."""
    alpha, beta = np.radians(np.asarray(alpha_deg, float)), np.radians(np.asarray(beta_deg, float))
    ca, sa, cb, sb = np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta)
    # R^T n for R = R_x(alpha) R_y(beta), written out for arrays of angles.
    x, y, z = normals[:, 0], normals[:, 1], normals[:, 2]
    shape = alpha.shape + (1,)
    ca, sa, cb, sb = (value.reshape(shape) for value in (ca, sa, cb, sb))
    turned_y = ca * y + sa * z
    turned_z_about_x = -sa * y + ca * z
    turned = np.stack([cb * x - sb * turned_z_about_x, np.broadcast_to(turned_y, turned_y.shape),
                       sb * x + cb * turned_z_about_x], axis=-1)
    return (_egi_at(reference_egi, turned) * weights).sum(axis=-1)


def egi_tilt_between(reference_depths: np.ndarray, current_depths: np.ndarray, kernel: int, pixel_size: float,
                     *, search_deg: float = 20.0, step_deg: float = 1.0) -> tuple[float, float, float]:
    """The paper's tilt measurement (eq. 14-17): the rotation R(alpha, beta) that best
    correlates the taught EGI with the current one, found on a grid of tilts
    (``step_deg`` over +-``search_deg``) and refined by a parabola through the best
    grid point and its neighbours on each axis, then a finer grid around it (a grid's
    argmax alone is off by up to half a step). Rotation about the beam is left to the
    image (log-polar): a plane's EGI is symmetric about its normal and cannot show it.

    Returns (alpha_deg, beta_deg, peak correlation over its value at zero tilt); NaN
    angles when either map has under ``MIN_KERNELS`` normals."""
    reference_normals, reference_weights = kernel_normals(reference_depths, kernel, pixel_size)
    normals, weights = kernel_normals(current_depths, kernel, pixel_size)
    if len(reference_normals) < MIN_KERNELS or len(normals) < MIN_KERNELS:
        return float("nan"), float("nan"), 0.0
    reference_egi = extended_gaussian_image(reference_normals, reference_weights)
    centre_alpha = centre_beta = 0.0
    span, step = search_deg, step_deg
    for _ in range(3):  # coarse grid, then two finer ones about the refined peak
        offsets = np.arange(-span, span + step / 2, step)
        alphas, betas = np.meshgrid(centre_alpha + offsets, centre_beta + offsets, indexing="ij")
        scores = egi_correlation(reference_egi, normals, weights, alphas, betas)
        row, col = np.unravel_index(np.argmax(scores), scores.shape)
        refined = []
        for index, line, centre in ((row, scores[:, col], alphas[row, col]), (col, scores[row, :], betas[row, col])):
            if 0 < index < len(line) - 1:
                curvature = line[index - 1] - 2 * line[index] + line[index + 1]
                shift = 0.5 * (line[index - 1] - line[index + 1]) / curvature if curvature < 0 else 0.0
                centre += float(np.clip(shift, -0.5, 0.5)) * step
            refined.append(centre)
        centre_alpha, centre_beta = refined
        span, step = 2 * step, step / 5
    peak = float(egi_correlation(reference_egi, normals, weights, np.array(centre_alpha), np.array(centre_beta)))
    at_zero = float(egi_correlation(reference_egi, normals, weights, np.array(0.0), np.array(0.0)))
    return centre_alpha, centre_beta, peak / max(at_zero, 1e-12)


# --------------------------------------------------------------------------------------
# Planning a sweep

#: Steps of the sweep, in depths of field: half a depth of field for the first, wide
#: sweep; three quarters when tracking (the peak fit spans +-1 step).
FIRST_STEP_DOF, TRACKING_STEP_DOF = 0.5, 0.75
#: Margin beyond the deepest and shallowest kernel, in depths of field: a focus curve
#: needs samples on both sides of its peak and enough contrast (MIN_FOCUS_CONTRAST).
MARGIN_DOF = 2.0


def plan_sweep(centre: float, depth_of_field: float, field: float, *, tilt_deg: tuple[float, float] | None = None,
               max_tilt_deg: float = 15.0, max_frames: int = 25,
               grid: tuple[float, float] | None = None) -> np.ndarray:
    """The working distances of the next focus sweep (same unit as ``centre``, the
    depth expected at the image centre; ``field``, the image's width on the sample).

    Without ``tilt_deg`` (the first sweep), wide enough for any tilt up to
    ``max_tilt_deg`` on both axes, at half a depth of field per frame. Tracking (the
    last measured tilts), only the depths the field spans at those tilts plus a margin,
    at three quarters of a depth of field per frame: a handful of frames near each
    kernel's focus, not a full sweep (fewer frames the flatter the view).

    ``grid`` (first working distance, step) puts the sweep on the taught sweep's
    working distances: each kernel's focus curve is then sampled at the same places as
    when it was taught, so the peak fit's small bias (which depends on where the peak
    falls between samples) is the same in both and cancels in the tilt difference. A
    sweep that would take more than ``max_frames`` at the grid's step is spread over
    ``max_frames`` instead, off the grid (far from the taught pose, where no pull cancels).
    """
    if not (np.isfinite([centre, depth_of_field, field]).all() and depth_of_field > 0 and field > 0):
        raise ValueError("centre, depth_of_field and field must be finite, the last two positive")
    if tilt_deg is None:
        spread = field * np.tan(np.radians(max_tilt_deg)) * 2
        step = FIRST_STEP_DOF * depth_of_field
    else:
        alpha, beta = np.radians(np.clip(np.abs(tilt_deg), 0, 80))
        spread = field * (np.tan(alpha) + np.tan(beta) / np.cos(alpha))
        step = TRACKING_STEP_DOF * depth_of_field
    span = spread + 2 * MARGIN_DOF * depth_of_field
    if grid is not None:
        origin, step = grid
        if not (np.isfinite([origin, step]).all() and step > 0):
            raise ValueError("grid must be a finite first working distance and a positive step")
        centre = origin + round((centre - origin) / step) * step
    frames = int(np.ceil(span / step)) + 1
    if frames > max_frames:
        frames, step = max_frames, span / (max_frames - 1)
    frames += (frames + 1) % 2  # odd: one frame at the centre
    return centre + (np.arange(frames) - frames // 2) * step


#: A teach that the wide sweeps cannot pin (:func:`wants_fine_sweeps`) sweeps the view
#: again at this step, in depths of field (half the first sweep's, on its grid), over
#: only the depths its kernels were found at: the frames land on the flanks of the
#: kernels' focus curves, where focus shows, not on blur far from every kernel's focus,
#: and the pull between samples (``SAMPLING_BIAS_STEPS``) is half as large. On the drift
#: pair's sparse particles, which four wide sweeps could not teach, one such sweep of 17
#: frames pins the tilts 1.5-2 times tighter than one wide sweep of 21.
FINE_STEP_DOF = 0.25
#: The most fine sweeps a teach pools after its wide ones.
MAX_FINE_TEACH_SWEEPS = 8


def wants_fine_sweeps(estimate: TiltEstimate, line_deg: float = MAX_TAUGHT_UNCERTAINTY_DEG) -> bool:
    """Whether a teach whose wide sweeps are done (:func:`wants_another_sweep` asks for no
    more) should sweep the view finely (:func:`plan_fine_sweep`): when its pooled tilts are
    over ``line_deg`` for their uncertainty alone, from kernels enough for a plane. One
    refused for another reason (too few kernels with a clear peak, depths that are not one
    plane) is not: finer sampling does not make texture appear."""
    worst = max(estimate.alpha_uncertainty_deg, estimate.beta_uncertainty_deg)
    # tilt_from_depths checks the uncertainty before the scatter: refused and over its
    # line, the uncertainty is what refused it.
    for_uncertainty = estimate.confidence > 0 or worst > MAX_TILT_UNCERTAINTY_DEG
    return bool(np.isfinite(worst)) and worst > line_deg and estimate.kernels_used >= MIN_KERNELS and for_uncertainty


def sampled_as_finely(working_distances, step: float) -> bool:
    """Whether a sweep's ``working_distances`` are at most ``step`` apart (a taught grid's;
    1 % slack for rounding): a run's sweep as fine as a fine teach's needs no finer one
    after it, and pools as many as that teach could."""
    distances = np.asarray(working_distances, dtype=np.float64)
    if distances.size < 2:
        return False
    return bool((distances[-1] - distances[0]) / (distances.size - 1) <= step * 1.01)


def plan_fine_sweep(depths: np.ndarray, wide_sweep, depth_of_field: float, max_frames: int = 25,
                    grid: tuple[float, float] | None = None) -> np.ndarray | None:
    """The working distances of a fine teach sweep (:data:`FINE_STEP_DOF`): on the wide
    sweep's grid at a fraction of its step, from ``MARGIN_DOF`` depths of field before the
    shallowest kernel ``depths`` found (NaN: none; those ``OUTLIER_SIGMAS`` robust standard
    deviations, or a depth of field, from their median are left out) to as far past the
    deepest. ``grid`` (first working distance, step): a fine grid already taught, which
    the sweep keeps to instead (a run's, whose own wide sweep may lie off it). None where
    the kernels span too much depth for ``max_frames`` at that step (a view tilted steeply
    across its field): the wide sweeps stand."""
    wide = np.asarray(wide_sweep, dtype=np.float64)
    found = np.asarray(depths, dtype=np.float64)
    found = found[np.isfinite(found)]
    if wide.size < 2 or found.size == 0 or not (np.isfinite(depth_of_field) and depth_of_field > 0):
        return None
    # Without the odd kernel read at the sweep's end (a marginal peak): the plane leaves
    # such kernels out too.
    middle = np.median(found)
    spread = max(OUTLIER_SIGMAS * 1.4826 * float(np.median(np.abs(found - middle))), depth_of_field)
    found = found[np.abs(found - middle) <= spread]
    if grid is not None:
        origin, step = float(grid[0]), float(grid[1])
    else:
        origin, wide_step = float(wide[0]), float(wide[1] - wide[0])
        # A whole fraction of the wide step, so the fine grid holds every wide sample.
        step = wide_step / max(1, round(wide_step / (FINE_STEP_DOF * depth_of_field)))
    margin = MARGIN_DOF * depth_of_field
    first = origin + np.floor((found.min() - margin - origin) / step) * step
    last = origin + np.ceil((found.max() + margin - origin) / step) * step
    frames = int(round((last - first) / step)) + 1
    if frames > max_frames:
        return None
    return first + np.arange(frames) * step


# --------------------------------------------------------------------------------------
# The view square on


#: Tilts (degrees, both axes) below which a frame is measured as it is, not resampled to
#: undo its foreshortening.
UNDO_FORESHORTENING_FROM_DEG = 0.05


def undoes_foreshortening(alpha_deg: float | None, beta_deg: float | None) -> bool:
    """Whether a frame seen at these tilts is resampled to undo its foreshortening: the
    tilts known and one of them at least :data:`UNDO_FORESHORTENING_FROM_DEG`."""
    return alpha_deg is not None and beta_deg is not None and \
        max(abs(alpha_deg), abs(beta_deg)) >= UNDO_FORESHORTENING_FROM_DEG


def _seen_through(alpha_deg: float, beta_deg: float) -> np.ndarray:
    alpha, beta = np.radians(alpha_deg), np.radians(beta_deg)
    return np.array([[np.cos(beta), 0.0], [np.sin(alpha) * np.sin(beta), np.cos(alpha)]])


def foreshortening(alpha_deg: float | None, beta_deg: float | None) -> np.ndarray:
    """A = [[cos beta, 0], [sin alpha sin beta, cos alpha]]: how a surface tilted by
    R_x(alpha) R_y(beta) is seen (orthographically), as the estimator undoes it; the
    identity where it does not (:func:`undoes_foreshortening`: the frame is then
    measured as it is)."""
    return _seen_through(alpha_deg, beta_deg) if undoes_foreshortening(alpha_deg, beta_deg) else np.eye(2)


def rows_seen_square_on(first_row: int, shape: tuple[int, int], alpha_deg: float, beta_deg: float) -> int:
    """The first row of a frame undone by :func:`undo_foreshortening` whose bicubic
    samples all come from the frame's rows from ``first_row`` on (the rows of a partial
    frame: what was scanned after a move settled). Seen through A, an output row reads
    input rows ``sin alpha sin beta`` per column apart across the frame and ``cos alpha``
    times as far from the centre: at 15 degrees on both axes a row reaches 17 rows up
    over a 512-px frame. Two rows more for the bicubic kernel."""
    rows, cols = shape
    forward = _seen_through(alpha_deg, beta_deg)
    centre_y, centre_x = (rows - 1) / 2, (cols - 1) / 2
    # Output row y reads rows centre_y + cos(alpha) (y - centre_y) + s (x - centre_x), x over the row.
    reach = abs(forward[1, 0]) * centre_x
    needed = first_row + 2
    return int(min(max(math.ceil(centre_y + (needed - centre_y + reach) / forward[1, 1]), first_row), rows))


def undo_foreshortening(frame: np.ndarray, alpha_deg: float, beta_deg: float) -> np.ndarray:
    """The frame as the surface would look square on, about the image centre: a surface
    tilted by R_x(alpha) R_y(beta) is seen (orthographically) through A
    (:func:`foreshortening`); this resamples the frame through A (bicubic). The rotation
    about the beam is then measured on it: on the raw frame of a surface tilted by 15
    degrees the log-polar angle was off by up to 14 degrees (the foreshortening is an
    anisotropic scale), on this one by 0.03 at most (``bench/tilt.py``)."""
    import cv2

    forward = _seen_through(alpha_deg, beta_deg)
    centre = (np.array(frame.shape[::-1], dtype=np.float64) - 1) / 2
    matrix = np.hstack([forward, (centre - forward @ centre)[:, None]])
    return cv2.warpAffine(np.asarray(frame, dtype=np.float32), matrix, frame.shape[::-1],
                          flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT)
