"""Focus sweeps with exactly known tilts, made from a real SEM image: the image is the
sample's texture on a tilted plane, blurred by a defocus model written apart from the
simulator (:mod:`semservo.simulation` shares no code, constant or model with this).

A tool for checking the tilts from focus (:func:`semservo.estimation.tilt.estimate_tilt`)
on textures nobody tuned on, with a blur the method was not developed with; used by
``bench/tilt_real.py`` and the tests, and useful on your own images before a session.

The model
---------
* Geometry: the plane is tilted by R = R_x(alpha) R_y(beta) (the convention of
  :mod:`semservo.estimation.tilt`) and turned by gamma about its own normal first (the
  stage's turn about the beam), seen orthographically: the texture is foreshortened
  through A = [[cos beta, 0], [sin alpha sin beta, cos alpha]] and the depth of the
  surface under image point (x, y) (um from the frame's centre) is
  ``centre + tan(alpha) y - tan(beta) x / cos(alpha)``. One texture pixel is one frame
  pixel at zero tilt; where the view needs texture beyond the image's edges, the image
  is mirrored there (``cv2.BORDER_REFLECT``).
* Defocus: a point of the surface at a distance d from the focal plane is blurred by a
  kernel whose width grows linearly with |d|: ``width_px = 2 |d| / depth_of_field``, so
  the blur is 1 px half a depth of field away. ``"gaussian"``: a Gaussian probe whose
  standard deviation is ``probe_px + width_px``. ``"disc"``: a uniform disc (pillbox) of
  radius ``width_px`` (the geometric cone of a beam of half-angle 2 pixels / depth of
  field), convolved with the in-focus Gaussian probe of ``probe_px``. ``"quadrature"``: a
  Gaussian whose standard deviation is ``sqrt(probe_px^2 + width_px^2)`` (the focused
  probe and the defocus adding in quadrature: as wide as ``"gaussian"`` far from focus,
  but with a smooth, round peak where ``"gaussian"`` has a cusp). The blur varies
  across the frame with the depth: the frame is blended, pixel by pixel, from the view
  blurred at neighbouring widths (linearly; widths 0.25 px apart up to 2 px, then 10 %
  apart).
* Noise: shot noise (Poisson, ``electrons`` per grey level at full scale 255) and
  Gaussian read noise, per frame (:func:`semservo.pairs.poisson_gaussian`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np

from semservo.pairs import poisson_gaussian

DEFOCUS_SHAPES = ("gaussian", "disc", "quadrature")


@dataclass(frozen=True)
class DefocusModel:
    """How a point out of focus is blurred (see the module's text)."""

    shape: str = "gaussian"
    depth_of_field_um: float = 2.5
    #: The probe at focus: a Gaussian's standard deviation in pixels.
    probe_px: float = 0.6

    def __post_init__(self):
        if self.shape not in DEFOCUS_SHAPES:
            raise ValueError(f"unknown defocus shape {self.shape!r}: {' or '.join(DEFOCUS_SHAPES)}")
        if not (self.depth_of_field_um > 0 and self.probe_px >= 0):
            raise ValueError("depth_of_field_um must be positive and probe_px not negative")

    def width_px(self, defocus_um):
        """The blur's width (px) at ``defocus_um`` from focus: 2 |d| / depth of field."""
        return 2.0 * np.abs(defocus_um) / self.depth_of_field_um

    def transfer(self, width_px: float, shape: tuple[int, int]) -> np.ndarray:
        """The blur's transfer function at ``width_px`` on the real-input half plane of
        an image of ``shape`` (its kernel centred on pixel (0, 0), periodic); complex64,
        kept for the next pose (do not write into it)."""
        return _transfer(self.shape, self.probe_px, float(width_px), tuple(shape))


@lru_cache(maxsize=128)
def _transfer(shape_name: str, probe_px: float, width_px: float, shape: tuple[int, int]) -> np.ndarray:
    v = np.fft.fftfreq(shape[0])[:, None]
    u = np.fft.rfftfreq(shape[1])[None, :]
    radius_squared = u * u + v * v
    if shape_name in ("gaussian", "quadrature"):
        sigma = probe_px + width_px if shape_name == "gaussian" else np.hypot(probe_px, width_px)
        transfer = np.exp(-2 * np.pi**2 * sigma**2 * radius_squared)
    else:
        transfer = np.exp(-2 * np.pi**2 * probe_px**2 * radius_squared)
        if width_px >= 0.05:
            transfer = np.fft.rfft2(disc_kernel(width_px, shape)) * transfer
    transfer = transfer.astype(np.complex64)
    transfer.flags.writeable = False
    return transfer


def disc_kernel(radius_px: float, shape: tuple[int, int], supersampling: int = 8) -> np.ndarray:
    """A uniform disc of ``radius_px`` (fractional), its area per pixel computed on a
    ``supersampling`` x ``supersampling`` grid within each pixel, normalised to sum 1,
    centred on pixel (0, 0) of a periodic ``shape`` canvas."""
    reach = int(np.ceil(radius_px)) + 1
    offsets = (np.arange(supersampling) + 0.5) / supersampling - 0.5
    pixels = np.arange(-reach, reach + 1)
    fine = (pixels[:, None] + offsets[None, :]).ravel()
    inside = (fine[:, None] ** 2 + fine[None, :] ** 2) <= radius_px**2
    side = pixels.size
    area = inside.reshape(side, supersampling, side, supersampling).mean(axis=(1, 3))
    kernel = np.zeros(shape)
    rows, cols = np.meshgrid(pixels % shape[0], pixels % shape[1], indexing="ij")
    np.add.at(kernel, (rows, cols), area)
    return kernel / kernel.sum()


def view_matrix(alpha_deg: float, beta_deg: float, gamma_deg: float) -> np.ndarray:
    """The 2 x 2 map from texture to image coordinates (x right, y down, about the
    centres): the texture turned by gamma counter-clockwise as displayed, then
    foreshortened through A = [[cos beta, 0], [sin alpha sin beta, cos alpha]]."""
    alpha, beta, gamma = np.radians([alpha_deg, beta_deg, gamma_deg])
    foreshortening = np.array([[np.cos(beta), 0.0], [np.sin(alpha) * np.sin(beta), np.cos(alpha)]])
    turn = np.array([[np.cos(gamma), np.sin(gamma)], [-np.sin(gamma), np.cos(gamma)]])
    return foreshortening @ turn


def plane_depth(shape: tuple[int, int], pixel_um: float, alpha_deg: float, beta_deg: float,
                centre_um: float = 0.0) -> np.ndarray:
    """The depth (um, along the beam away from the lens) of the tilted plane under each
    pixel of a frame of ``shape``: centre + tan(alpha) y - tan(beta) x / cos(alpha)."""
    alpha, beta = np.radians([alpha_deg, beta_deg])
    y = (np.arange(shape[0]) - (shape[0] - 1) / 2)[:, None] * pixel_um
    x = (np.arange(shape[1]) - (shape[1] - 1) / 2)[None, :] * pixel_um
    return centre_um + np.tan(alpha) * y - np.tan(beta) * x / np.cos(alpha)


def blur_widths(largest_px: float) -> np.ndarray:
    """The widths the view is blurred at before blending: 0.25 px apart up to 2 px, then
    10 % apart, up to ``largest_px``."""
    widths = list(np.arange(0.0, 2.0, 0.25))
    while widths[-1] < largest_px:
        widths.append(max(widths[-1] * 1.1, 2.0))
    return np.asarray(widths)


@dataclass
class TiltedTexture:
    """A real image as the texture of a plane at one pose, ready to be scanned at any
    working distance (:meth:`frame`, :meth:`sweep`).

    ``texture``: grey levels (0-255 scale); ``shape``: the frames'; ``pixel_um``: the
    frame's pixel on the sample; ``pose``: (alpha, beta, gamma) degrees;
    ``centre_depth_um``: the plane's depth under the frame's centre.
    """

    texture: np.ndarray
    model: DefocusModel
    pixel_um: float
    shape: tuple[int, int] = (512, 512)
    pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    centre_depth_um: float = 0.0
    #: The blur the view is made for (px): beyond it, the widest level is used.
    largest_width_px: float = 24.0
    _stack: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self):
        self.texture = np.asarray(self.texture, dtype=np.float32)
        if self.texture.ndim != 2:
            raise ValueError("the texture must be a 2-D grey image")
        self.widths = blur_widths(self.largest_width_px)
        self.margin = int(np.ceil(3 * (self.model.probe_px + self.widths[-1]))) + 4
        self.depth = plane_depth(self.shape, self.pixel_um, self.pose[0], self.pose[1], self.centre_depth_um)
        canvas_shape = (self.shape[0] + 2 * self.margin, self.shape[1] + 2 * self.margin)
        # Image (canvas) -> texture coordinates, for warpAffine's inverse map.
        to_texture = np.linalg.inv(view_matrix(*self.pose))
        canvas_centre = (np.array(canvas_shape[::-1], dtype=np.float64) - 1) / 2
        texture_centre = (np.array(self.texture.shape[::-1], dtype=np.float64) - 1) / 2
        matrix = np.hstack([to_texture, (texture_centre - to_texture @ canvas_centre)[:, None]])
        self.sharp = cv2.warpAffine(self.texture, matrix, canvas_shape[::-1], flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                                    borderMode=cv2.BORDER_REFLECT)
        self._spectrum = np.fft.rfft2(self.sharp.astype(np.float32))  # float32 transforms: half the time

    def _levels_through(self, index: int) -> np.ndarray:
        """The view blurred at ``widths[0..index]`` or more (made as needed, kept),
        cropped to the frame: levels x rows x cols."""
        made = 0 if self._stack is None else len(self._stack)
        if made <= index:
            canvas_shape, m = self.sharp.shape, self.margin
            new = np.empty((index + 1 - made,) + self.shape, np.float32)
            for offset, level in enumerate(range(made, index + 1)):
                transfer = self.model.transfer(float(self.widths[level]), canvas_shape)
                blurred = np.fft.irfft2(self._spectrum * transfer, s=canvas_shape)
                new[offset] = blurred[m:m + self.shape[0], m:m + self.shape[1]]
            self._stack = new if self._stack is None else np.concatenate([self._stack, new])
        return self._stack

    def noiseless_frame(self, working_distance_um: float) -> np.ndarray:
        """The frame at ``working_distance_um`` without noise: each pixel blended from the
        two blur levels around its own blur width."""
        width = np.minimum(self.model.width_px(self.depth - working_distance_um), self.widths[-1])
        upper = np.clip(np.searchsorted(self.widths, width, side="right"), 1, len(self.widths) - 1)
        lower = upper - 1
        fraction = ((width - self.widths[lower]) / (self.widths[upper] - self.widths[lower])).astype(np.float32)
        levels = self._levels_through(int(upper.max()))
        below = np.take_along_axis(levels, lower[np.newaxis], axis=0)[0]
        above = np.take_along_axis(levels, upper[np.newaxis], axis=0)[0]
        return below + fraction * (above - below)

    def frame(self, working_distance_um: float, rng: np.random.Generator, electrons: float = 1000.0,
              read_noise: float = 2.0) -> np.ndarray:
        """The frame at ``working_distance_um`` with shot and read noise."""
        return poisson_gaussian(self.noiseless_frame(working_distance_um), electrons, read_noise, rng)

    def sweep(self, working_distances_um, rng: np.random.Generator, electrons: float = 1000.0,
              read_noise: float = 2.0) -> np.ndarray:
        """The frames at each working distance (frames, rows, cols)."""
        return np.stack([self.frame(float(distance), rng, electrons, read_noise) for distance in working_distances_um])


def _offset_frames(scene: TiltedTexture, distance_um: float, shift_um: float) -> tuple[np.ndarray, np.ndarray]:
    """The noiseless frames at ``distance_um`` with the plane moved ``shift_um`` deeper and
    nearer (the same as the working distance moved the other way)."""
    deeper = scene.noiseless_frame(distance_um - shift_um).astype(np.float64)
    nearer = scene.noiseless_frame(distance_um + shift_um).astype(np.float64)
    return deeper, nearer


def _pixel_noise(mean: np.ndarray, electrons: float, read_noise: float) -> np.ndarray:
    """The variance of a pixel (grey levels^2) of noise-free level ``mean``: shot noise of
    ``electrons`` per grey level at full scale and ``read_noise`` (:func:`poisson_gaussian`)."""
    return np.maximum(mean, 0.0) * 255.0 / electrons + read_noise**2


def _tilt_errors(scene: TiltedTexture, information: np.ndarray, y: np.ndarray, x: np.ndarray) -> tuple[float, float]:
    """The standard errors (degrees) of alpha and beta of a plane z = c + gx x + gy y whose
    points (``x``, ``y``, um, flat arrays) have depth information ``information``
    (1 / um^2 each): the slopes' covariance is (X^T I X)^-1, X the rows (1, x, y), and
    the tilts follow as the module's geometry relates them to the slopes
    (alpha = atan(gy), beta = -atan(cos(alpha) gx)) at the scene's pose. Infinite for a
    slope the points cannot pin at all (no information, or all of it on one row or one
    column of points)."""
    design = np.column_stack([np.ones(x.size), x, y])
    normal = (design * information[:, None]).T @ design
    covariance = np.linalg.pinv(normal)
    # A slope along which X^T I X has no extent is not pinned: the pseudo-inverse would
    # give it a variance of 0 instead of infinity.
    extents, directions = np.linalg.eigh(normal)
    unpinned = directions[:, extents <= 1e-12 * max(float(extents.max()), 1e-300)]
    variances = np.where(np.any(np.abs(unpinned) > 1e-9, axis=1), np.inf, np.diag(covariance))
    alpha, beta = np.radians(scene.pose[:2])
    slope_y, slope_x = np.tan(alpha), -np.tan(beta) / np.cos(alpha)
    cos_alpha = np.cos(alpha)
    alpha_error = np.sqrt(variances[2]) / (1 + slope_y**2)
    beta_error = np.sqrt(variances[1]) * cos_alpha / (1 + (cos_alpha * slope_x) ** 2)
    return float(np.degrees(alpha_error)), float(np.degrees(beta_error))


def _kernel_grid(scene: TiltedTexture, kernel: int) -> tuple[int, int, np.ndarray, np.ndarray]:
    """Rows and columns of whole kernels in a frame, and their centres' y, x (um from the
    frame's centre, flat, row-major)."""
    rows, cols = scene.shape[0] // kernel, scene.shape[1] // kernel
    y = ((np.arange(rows) + 0.5) * kernel - rows * kernel / 2) * scene.pixel_um
    x = ((np.arange(cols) + 0.5) * kernel - cols * kernel / 2) * scene.pixel_um
    grid_y, grid_x = np.meshgrid(y, x, indexing="ij")
    return rows, cols, grid_y.ravel(), grid_x.ravel()


def information_tilt_bound(scene: TiltedTexture, information: np.ndarray, kernel: int = 32) -> tuple[float, float]:
    """The standard errors (alpha, beta; degrees) no unbiased plane through the kernels'
    depths can beat when each kernel's depth carries the Fisher ``information`` (kernel
    rows x cols, 1 / um^2: :func:`normalized_variance_information`,
    :func:`measure_information`): the slopes' covariance (X^T I X)^-1, X the kernels'
    centres (1, x, y in um), carried into the tilts."""
    _, _, y, x = _kernel_grid(scene, kernel)
    return _tilt_errors(scene, np.asarray(information, dtype=np.float64).ravel(), y, x)


def tilt_bound(scene: TiltedTexture, working_distances_um, kernel: int = 32, electrons: float = 1000.0,
               read_noise: float = 2.0, shift_um: float = 0.05) -> tuple[float, float]:
    """The Cramer-Rao bound of the tilts from one focus sweep of ``scene`` read through
    eq. 13's measure (alpha, beta; degrees): :func:`information_tilt_bound` of
    :func:`normalized_variance_information`.

    Why: how well a texture can pin the tilts through eq. 13 is a property of the
    texture, the blur and the dose, not of how the focus curves are read; the bound says
    whether a refusal is the reading's or the measure's. What no estimator at all can beat,
    whatever it measures, is :func:`pixel_tilt_bound`; another measure's bound,
    :func:`measure_tilt_bound`."""
    information = normalized_variance_information(scene, working_distances_um, kernel, electrons, read_noise, shift_um)
    return information_tilt_bound(scene, information, kernel)


def normalized_variance_information(scene: TiltedTexture, working_distances_um, kernel: int = 32,
                                    electrons: float = 1000.0, read_noise: float = 2.0,
                                    shift_um: float = 0.05) -> np.ndarray:
    """The Fisher information (1 / um^2, kernel rows x cols) each kernel's eq. 13 focus
    curve carries about its depth in one focus sweep of ``scene``: what
    :func:`tilt_bound` is built on, and what one kernel's depth read through eq. 13 can
    at best be pinned to (1 / sqrt of it). The measure is each ``kernel`` x ``kernel``
    block's variance over its mean, frame by frame, under this module's noise.

    Each kernel's depth is pinned by the Fisher information of its focus curve,
    sum over the frames of (dS / dz)^2 / var(S): S = V / m the noise-free measure (V the
    block's variance, m its mean), its change with the kernel's depth z read off the
    noiseless frames with the plane moved ``shift_um`` deeper and nearer (the same as
    every working distance moved the other way). var(S) is carried from each pixel's own
    noise variance s_i (shot noise of ``electrons`` per grey level at full scale at that
    pixel's level, and ``read_noise``) to first order, its P pixels' deviations d_i from
    the mean taken as fixed:

        var(V) = sum(4 d_i^2 s_i + 2 s_i^2) / P^2,   var(m) = sum(s_i) / P^2,
        cov(V, m) = sum(2 d_i s_i) / P^2,
        var(S) = var(V) / m^2 + V^2 var(m) / m^4 - 2 V cov(V, m) / m^3.

    Why per pixel: shot noise is largest where the picture is bright, and on sparse
    bright particles that is where the deviations are too; the noise of the kernel's
    mean level alone under-stated var(S) there (the bounds 4-8 % tighter than their Monte
    Carlo, :func:`measure_information`, on the drift pair; now within about 1 %)."""
    distances = np.asarray(working_distances_um, dtype=np.float64)
    rows, cols, _, _ = _kernel_grid(scene, kernel)
    pixels = kernel * kernel

    def measures(offset_um: float, with_variance: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """eq. 13's noise-free measure and (``with_variance``) its variance under the
        pixels' noise, frames x kernels."""
        measure, variance = [], []
        for distance in distances:
            frame = scene.noiseless_frame(float(distance) - offset_um)[:rows * kernel, :cols * kernel].astype(np.float64)
            blocks = frame.reshape(rows, kernel, cols, kernel).transpose(0, 2, 1, 3).reshape(rows * cols, pixels)
            block_mean = np.maximum(blocks.mean(axis=1), 1e-9)
            deviation = blocks - block_mean[:, None]
            block_variance = np.mean(deviation**2, axis=1)
            measure.append(block_variance / block_mean)
            if not with_variance:
                continue
            pixel_variance = _pixel_noise(blocks, electrons, read_noise)
            variance_of_variance = np.sum(4 * deviation**2 * pixel_variance + 2 * pixel_variance**2, axis=1) / pixels**2
            variance_of_mean = np.sum(pixel_variance, axis=1) / pixels**2
            covariance = np.sum(2 * deviation * pixel_variance, axis=1) / pixels**2
            variance.append(variance_of_variance / block_mean**2 + block_variance**2 * variance_of_mean / block_mean**4
                            - 2 * block_variance * covariance / block_mean**3)
        return np.array(measure), (np.array(variance) if with_variance else None)

    _, variance = measures(0.0, with_variance=True)
    deeper, _ = measures(shift_um, with_variance=False)  # only the slope is wanted of these
    nearer, _ = measures(-shift_um, with_variance=False)
    slope = (deeper - nearer) / (2 * shift_um)
    return np.sum(slope**2 / np.maximum(variance, 1e-300), axis=0).reshape(rows, cols)


def pixel_tilt_bound(scene: TiltedTexture, working_distances_um, electrons: float = 1000.0,
                     read_noise: float = 2.0, shift_um: float = 0.05) -> tuple[float, float]:
    """The Cramer-Rao bound of the tilts from the pixels of one focus sweep of ``scene``
    (alpha, beta; degrees): what no estimator can beat, whatever it measures, even one
    that knew the sharp texture and the blur (a real one knows neither, so it does worse).

    Each pixel p at depth z_p = c + gx x_p + gy y_p carries the Fisher information
    sum over the frames of (dI_p / dz)^2 / var(I_p) about its depth: I_p its noise-free
    grey level, dI_p / dz read off the noiseless frames with the plane moved ``shift_um``
    deeper and nearer, var(I_p) its shot and read noise (:func:`poisson_gaussian`); the
    plane's slopes have the covariance (X^T I X)^-1 over the pixels, and the tilts follow
    as in :func:`tilt_bound`.

    Why: :func:`tilt_bound` is eq. 13's; this one says how much a better measure could
    gain at all (on the six pictures of ``bench/tilt_bounds.py`` eq. 13's bound is 1.6-2.5
    times this one: it keeps 16-41 % of the pixels' information)."""
    information = np.zeros(scene.shape, dtype=np.float64)
    for distance in np.asarray(working_distances_um, dtype=np.float64):
        deeper, nearer = _offset_frames(scene, float(distance), shift_um)
        noise_free = scene.noiseless_frame(float(distance)).astype(np.float64)
        information += ((deeper - nearer) / (2 * shift_um)) ** 2 / _pixel_noise(noise_free, electrons, read_noise)
    y = (np.arange(scene.shape[0]) - (scene.shape[0] - 1) / 2) * scene.pixel_um
    x = (np.arange(scene.shape[1]) - (scene.shape[1] - 1) / 2) * scene.pixel_um
    grid_y, grid_x = np.meshgrid(y, x, indexing="ij")
    return _tilt_errors(scene, information.ravel(), grid_y.ravel(), grid_x.ravel())


def measure_tilt_bound(scene: TiltedTexture, working_distances_um, measure, kernel: int = 32,
                       electrons: float = 1000.0, read_noise: float = 2.0, realizations: int = 12,
                       rng: np.random.Generator | None = None, shift_um: float = 0.05) -> tuple[float, float]:
    """The Cramer-Rao bound of the tilts from one focus sweep of ``scene`` read through
    any focus measure (alpha, beta; degrees), as :func:`tilt_bound` is eq. 13's: each
    kernel's information sum over the frames of (dS / dz)^2 / var(S), the slope from the
    noiseless frames and var(S) from ``realizations`` noisy frames (Monte Carlo,
    :func:`measure_information`: each frame's term within about 1 / sqrt(realizations /
    2) of the truth, a kernel's sum over the sweep closer).

    ``measure``: a frame (float32, rows x cols) -> the measure of each whole ``kernel`` x
    ``kernel`` block (rows // kernel, cols // kernel).

    Why: to weigh a candidate measure against eq. 13 on a texture before building an
    estimator on it (``bench/tilt_bounds.py``)."""
    information = measure_information(scene, working_distances_um, measure, kernel, electrons, read_noise,
                                      realizations, rng, shift_um)
    return information_tilt_bound(scene, information, kernel)


def measure_information(scene: TiltedTexture, working_distances_um, measure, kernel: int = 32,
                        electrons: float = 1000.0, read_noise: float = 2.0, realizations: int = 12,
                        rng: np.random.Generator | None = None, shift_um: float = 0.05) -> np.ndarray:
    """The Fisher information (1 / um^2, kernel rows x cols) each kernel's focus curve by
    ``measure`` carries about its depth in one focus sweep of ``scene``, by Monte Carlo as
    :func:`measure_tilt_bound` (built on it) describes: sum over the frames of
    (dS / dz)^2 / var(S), 1 / var(S) taken as (n - 3) / (n - 1) over the sample variance
    of the n = ``realizations`` noisy frames (at least 4): 1 / a sample variance
    over-states 1 / the variance by (n - 1) / (n - 3) on average (the inverse
    chi-square's mean; 22 % at 12 frames, which made the bounds 10 % too tight); none
    where the noisy frames all gave one value (a clamped measure). Why
    apart: a kernel's depth read from that curve scatters at least 1 / sqrt of it, so it
    says how much each kernel's reading loses (``bench/tilt_bounds.py``'s budget)."""
    if realizations < 4:
        raise ValueError(f"measure_information needs at least 4 noisy frames per working distance, not {realizations}")
    rng = np.random.default_rng(0) if rng is None else rng
    rows, cols, _, _ = _kernel_grid(scene, kernel)
    information = np.zeros(rows * cols, dtype=np.float64)
    for distance in np.asarray(working_distances_um, dtype=np.float64):
        deeper, nearer = _offset_frames(scene, float(distance), shift_um)
        slope = (np.asarray(measure(deeper.astype(np.float32)), dtype=np.float64)
                 - np.asarray(measure(nearer.astype(np.float32)), dtype=np.float64)).ravel() / (2 * shift_um)
        noisy = np.array([np.asarray(measure(scene.frame(float(distance), rng, electrons, read_noise)),
                                     dtype=np.float64).ravel() for _ in range(realizations)])
        spread = noisy.var(axis=0, ddof=1)
        # A measure the noise never moved was clamped (eq. 13 reads 0 wherever a kernel's
        # mean is not above 0, as in a black hole): it cannot see the depth either, and its
        # noise-free slope there (a variance over a mean near 0) is meaningless.
        information += np.divide(slope**2, spread, out=np.zeros_like(spread), where=spread > 0)
    return information.reshape(rows, cols) * (realizations - 3) / (realizations - 1)
