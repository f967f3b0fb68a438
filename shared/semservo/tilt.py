"""Out-of-plane tilts from focus (Marturi et al., section II-B-2): depth from focus per
kernel (eq. 13), and the two tilts from a robust plane fit to the kernel depths.

The paper turns the kernel depths into a point cloud, an extended Gaussian image and a
rotation found by correlation on SO(3) (eq. 14-17). For a planar sample the same two
angles are the slopes of the depth map, so a least-squares plane through the kernel
depths (robust to kernels whose focus peak is wrong) gives them directly; that is what
this module does. Small pure functions on arrays, no hidden state.

Sign convention (a contract)
----------------------------
Image axes as :mod:`semservo.estimation`: x along columns (right), y along rows (down);
z along the beam, away from the lens, so that (x, y, z) is right-handed and a larger z
is a larger working distance. ``alpha_deg`` is the rotation about x and ``beta_deg`` the
rotation about y, by the right-hand rule: with alpha > 0 the lower part of the image is
farther from the lens (depth grows with y: dz/dy = tan alpha); with beta > 0 the right
part is nearer (dz/dx = -tan beta).
"""

from __future__ import annotations

from dataclasses import dataclass

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


def focus_peaks(curves: np.ndarray, working_distances: np.ndarray) -> np.ndarray:
    """Each kernel's depth: the working distance of its focus peak, to a fraction of a
    step (a parabola through the highest sample and its two neighbours, on evenly
    spaced working distances). NaN where the curve has no clear peak: flat (the peak
    under ``MIN_FOCUS_CONTRAST`` times the lowest value) or highest at either end of
    the sweep (the focus lies outside it)."""
    working_distances = np.asarray(working_distances, dtype=np.float64)
    frames = curves.shape[0]
    best = np.argmax(curves, axis=0)
    highest = np.take_along_axis(curves, best[np.newaxis], axis=0)[0]
    lowest = curves.min(axis=0)
    inside = (best > 0) & (best < frames - 1)
    clear = inside & (highest > MIN_FOCUS_CONTRAST * np.maximum(lowest, 1e-12))
    index = np.clip(best, 1, frames - 2)
    below = np.take_along_axis(curves, (index - 1)[np.newaxis], axis=0)[0]
    at = np.take_along_axis(curves, index[np.newaxis], axis=0)[0]
    above = np.take_along_axis(curves, (index + 1)[np.newaxis], axis=0)[0]
    curvature = below - 2 * at + above
    offset = np.where(curvature < 0, 0.5 * (below - above) / np.where(curvature < 0, curvature, -1.0), 0.0)
    step = (working_distances[-1] - working_distances[0]) / (frames - 1)
    depths = working_distances[index] + np.clip(offset, -0.5, 0.5) * step
    return np.where(clear & (curvature < 0), depths, np.nan)


def fit_plane(depths: np.ndarray, kernel: int, pixel_size: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares plane depth = c + gx x + gy y through the kernels with a depth (x, y
    the kernel centres relative to the image centre, in the sweep's unit via
    ``pixel_size``), refitted once without the kernels off it by more than
    ``OUTLIER_SIGMAS`` robust standard deviations. Returns ((c, gx, gy), the mask of
    kernels used, RMS residual)."""
    kernel_rows, kernel_cols = depths.shape
    centre_y, centre_x = kernel_rows * kernel / 2, kernel_cols * kernel / 2
    y = ((np.arange(kernel_rows) + 0.5) * kernel - centre_y) * pixel_size
    x = ((np.arange(kernel_cols) + 0.5) * kernel - centre_x) * pixel_size
    grid_y, grid_x = np.meshgrid(y, x, indexing="ij")
    used = np.isfinite(depths)
    coefficients = np.zeros(3)
    for _ in range(2):
        if used.sum() < 3:
            break
        design = np.column_stack([np.ones(used.sum()), grid_x[used], grid_y[used]])
        coefficients = np.linalg.lstsq(design, depths[used], rcond=None)[0]
        residuals = depths - (coefficients[0] + coefficients[1] * grid_x + coefficients[2] * grid_y)
        spread = 1.4826 * np.median(np.abs(residuals[used]))
        keep = used & (np.abs(residuals) <= OUTLIER_SIGMAS * max(spread, 1e-12))
        if keep.sum() == used.sum():
            break
        used = keep
    residuals = depths - (coefficients[0] + coefficients[1] * grid_x + coefficients[2] * grid_y)
    rms = float(np.sqrt(np.mean(residuals[used] ** 2))) if used.any() else float("nan")
    return coefficients, used, rms


def estimate_tilt(sweep, working_distances, pixel_size: float, kernel: int = 32) -> TiltEstimate:
    """The two tilts from a focus sweep: frames of the same field at the working
    distances ``working_distances`` (evenly spaced, increasing, same unit as
    ``pixel_size``: e.g. um and um per pixel).

    ValueError for input that cannot be a sweep (under 3 frames, a length mismatch,
    unevenly spaced or non-finite distances, non-finite pixels, kernels that do not fit).
    A sweep that cannot tell the tilts (too few kernels with a clear focus peak: a
    flat, featureless scene, or a sweep that misses focus) gives confidence 0 and the
    reason, never a made-up angle (the angles are NaN).
    """
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
    depths = focus_peaks(focus_curves(sweep, kernel), working_distances)
    total = depths.size
    clear = int(np.isfinite(depths).sum())
    if clear < MIN_KERNELS:
        return TiltEstimate(float("nan"), float("nan"), float("nan"), clear, total, float("nan"), 0.0,
                            f"only {clear} of {total} kernels have a clear focus peak (at least {MIN_KERNELS} "
                            "are needed): flat content, or focus outside the sweep")
    (centre, slope_x, slope_y), used, rms = fit_plane(depths, kernel, pixel_size)
    alpha = float(np.degrees(np.arctan(slope_y)))
    beta = float(np.degrees(np.arctan(-slope_x)))
    # Trust falls as the depths scatter about the plane by a sizeable part of a step.
    step = float(steps.mean())
    confidence = float(np.exp(-rms / step)) if np.isfinite(rms) else 0.0
    return TiltEstimate(alpha, beta, float(centre), int(used.sum()), total, rms, confidence)
