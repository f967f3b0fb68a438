"""The simulated SEM: a raster scan of a sample whose pose changes while it is scanned.

Facts from ``shared/reference/sem-imaging.md``:

* Pixel size on the sample P = D / G (paper eq. 43), D = 212.3 um for 512 pixels.
* Probe: a Gaussian point-spread function (sigma ~0.7 px in focus), optionally
  astigmatic. Defocus: the beam widens by alpha |z - WD| (alpha the beam half-angle,
  the aperture's radius over the working distance: 7.2 mrad by default, 40 mrad in the
  small-depth-of-field ``tilts`` preset), so the depth of field, where that blur
  reaches a pixel, is DoF = 2 P / alpha: 59 um at x1000 by default, 12 um at x5000.
* Tilt (the rotation-and-tilt stage, :mod:`semservo.simulation.goniometer`): the
  surface is turned by alpha about the image's x axis and beta about its y axis, about a
  pivot below the surface, and projected orthographically: the field is foreshortened
  by cos alpha along y and cos beta along x, shifted by the pivot's lever, and its depth
  changes across the field (dz/dy = tan alpha, dz/dx = -tan beta, :mod:`semservo.estimation.tilt`'s
  convention), so parts of a tilted image are out of focus.
* Raster: pixels are acquired one at a time, dwell plus dead time each, lines end with a
  fly-back. Each line, and each pixel's time within it, sees the pose the stage has at
  that moment, so motion during a scan shears, stretches or repeats the content.
* Noise: Poisson in the collected electrons (their number grows with dwell) plus
  Gaussian amplifier noise integrated over the same dwell, so SNR grows as
  sqrt(dwell). Output saturates at 8/16 bit.

Rendering uses a precomputed stack of blurred copies of the sample (one per blur level)
and per-pixel bilinear sampling (cv2.remap), so a frame never re-rasterizes the scene.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from semservo.config import pixel_size_nm
from semservo.simulation.goniometer import PIVOT_DEPTH_UM
from semservo.simulation.scenes import Sample, rasterize

#: The nominal working distance (mm) and the default objective aperture (diameter, um):
#: a beam half-angle of 7.2 mrad, DoF = 2 P / alpha ~59 um at x1000 (textbook example).
NOMINAL_WORKING_DISTANCE_MM = 10.0
DEFAULT_APERTURE_UM = 144.0


def beam_half_angle(aperture_um: float, working_distance_mm: float) -> float:
    """alpha = aperture radius / working distance (rad)."""
    return aperture_um / 2 / (working_distance_mm * 1000.0)


BEAM_HALF_ANGLE = beam_half_angle(DEFAULT_APERTURE_UM, NOMINAL_WORKING_DISTANCE_MM)
#: Blur levels of the stack (sigma in image pixels); a pixel blends its two neighbours.
BLUR_LEVELS_PX = (0.0, 1.0, 2.0, 4.0, 8.0, 16.0)
#: Electrons collected per ns of dwell at full yield (sets the SNR per dwell time).
ELECTRONS_PER_NS = 3.0
#: Amplifier noise, as a variance in electrons per ns of dwell: integrated over the
#: dwell like the signal, so SNR still grows as sqrt(dwell).
AMPLIFIER_VARIANCE_PER_NS = 0.3


@dataclass(frozen=True)
class ScanSettings:
    """What a scan generator is told: scan speed, magnification, focus, levels."""

    dwell_ns: float = 720.0
    magnification: float = 1200.0
    rows: int = 512
    cols: int = 512
    # Focus: the working distance's offset (um) from the nominal one, which focuses on the
    # untilted stage's reference surface; larger is farther from the lens. -10 focuses on
    # the top of the micropart's 10 um bar.
    working_distance_um: float = -10.0
    # The objective aperture's diameter (um); None: the SEM's own (its preset's). With the
    # working distance it sets the beam half-angle, hence the depth of field.
    aperture_um: float | None = None
    brightness: float = 0.0  # offset, fraction of full scale
    contrast: float = 1.0  # gain
    bit_depth: int = 8
    pixel_dead_ns: float = 50.0
    # Line overhead (fly-back and line sync). 500 us reproduces the paper's frame rates:
    # 2.2 frames/s at 720 ns/px and 3.1 at 180 ns/px for 512 x 512.
    flyback_us: float = 500.0
    probe_sigma_px: float = 0.7
    astigmatism: float = 1.0  # ratio of the probe's two widths
    astigmatism_angle_deg: float = 0.0

    @property
    def pixel_um(self) -> float:
        return pixel_size_nm(self.magnification, self.cols) / 1000.0

    @property
    def line_time_s(self) -> float:
        return self.cols * (self.dwell_ns + self.pixel_dead_ns) * 1e-9 + self.flyback_us * 1e-6

    @property
    def frame_time_s(self) -> float:
        return self.rows * self.line_time_s


@dataclass(frozen=True)
class Pose:
    """Where the sample is: stage x, y, z (um) and the simulated rotation stage (deg)."""

    x_um: float = 0.0
    y_um: float = 0.0
    z_um: float = 0.0
    rotation_deg: float = 0.0
    tilt_x_deg: float = 0.0
    tilt_y_deg: float = 0.0


def sample_point(pose: Pose, image_x_um: float, image_y_um: float,
                 pivot_depth_um: float = PIVOT_DEPTH_UM) -> tuple[float, float]:
    """The sample point (um, the sample's own coordinates) that the image point
    (``image_x_um``, ``image_y_um``, from the image centre) shows at ``pose``: the
    geometry :meth:`SEM.render` maps every pixel through (stage shift, the tilt cradle
    about its pivot, seen orthographically, then the turn about the beam)."""
    alpha, beta = math.radians(pose.tilt_x_deg), math.radians(pose.tilt_y_deg)
    relative_x, relative_y = image_x_um - pose.x_um, image_y_um - pose.y_um
    u = (relative_x + pivot_depth_um * math.sin(beta)) / math.cos(beta)
    v = (relative_y - math.sin(alpha) * math.sin(beta) * u - pivot_depth_um * math.sin(alpha) * math.cos(beta)) \
        / math.cos(alpha)
    theta = math.radians(pose.rotation_deg)
    return math.cos(theta) * u - math.sin(theta) * v, math.sin(theta) * u + math.cos(theta) * v


def image_point(pose: Pose, sample_x_um: float, sample_y_um: float,
                pivot_depth_um: float = PIVOT_DEPTH_UM) -> tuple[float, float]:
    """Where the sample point (um) appears in the image at ``pose`` (um from the image
    centre): the inverse of :func:`sample_point`."""
    theta = math.radians(pose.rotation_deg)
    u = math.cos(theta) * sample_x_um + math.sin(theta) * sample_y_um
    v = -math.sin(theta) * sample_x_um + math.cos(theta) * sample_y_um
    alpha, beta = math.radians(pose.tilt_x_deg), math.radians(pose.tilt_y_deg)
    relative_x = u * math.cos(beta) - pivot_depth_um * math.sin(beta)
    relative_y = (v * math.cos(alpha) + math.sin(alpha) * math.sin(beta) * u
                  + pivot_depth_um * math.sin(alpha) * math.cos(beta))
    return relative_x + pose.x_um, relative_y + pose.y_um


def view_error_px(pose: Pose, taught: Pose, pixel_um: float,
                  pivot_depth_um: float = PIVOT_DEPTH_UM) -> tuple[float, float]:
    """How far (px, x right and y down) the sample point at the image centre in the
    ``taught`` pose has moved in the image at ``pose``: the positioning error the image
    shows. Without tilts it is the stage's error; with tilts it also holds the view
    shift of the tilt cradle's pivot, which x and y make up for."""
    point = sample_point(taught, 0.0, 0.0, pivot_depth_um)
    x_um, y_um = image_point(pose, *point, pivot_depth_um)
    return x_um / pixel_um, y_um / pixel_um


@dataclass
class _BlurStack:
    sample: Sample
    levels: list  # intensity blurred to each BLUR_LEVELS_PX (in image pixels)


@dataclass
class SEM:
    """Images one scene. ``render`` is pure given its inputs (and the noise generator)."""

    scene: str = "micropart"
    seed: int = 2013
    extent_um: float | None = None
    beam_half_angle: float = BEAM_HALF_ANGLE  # a larger aperture or shorter WD: less DoF
    working_distance_mm: float = NOMINAL_WORKING_DISTANCE_MM  # nominal: an aperture becomes a half-angle here
    pivot_depth_um: float = PIVOT_DEPTH_UM  # the tilt axes' depth below the surface
    #: A real picture as the sample (:class:`semservo.simulation.sample_image.SampleImage`)
    #: instead of the built-in ``scene``.
    sample_image: object | None = None
    _stacks: dict = field(default_factory=dict)
    charge: np.ndarray = field(default_factory=lambda: np.zeros((64, 64), np.float32))

    @classmethod
    def for_preset(cls, preset, seed: int, sample_image=None) -> "SEM":
        """The SEM of a :class:`semservo.simulation.world.Preset`: its scene (or a real
        picture as the sample), aperture and working distance."""
        return cls(preset.scene, seed, beam_half_angle=beam_half_angle(preset.aperture_um, preset.working_distance_mm),
                   working_distance_mm=preset.working_distance_mm, sample_image=sample_image)

    def half_angle(self, settings: ScanSettings) -> float:
        """The beam half-angle of this scan: its aperture's, or the SEM's own."""
        if settings.aperture_um is None:
            return self.beam_half_angle
        return beam_half_angle(settings.aperture_um, self.working_distance_mm + settings.working_distance_um / 1000)

    def _stack(self, settings: ScanSettings) -> _BlurStack:
        """The sample sampled at half the image pixel, blurred to each level (cached per
        magnification, probe and field size)."""
        key = (round(settings.magnification, 3), settings.cols, settings.probe_sigma_px,
               settings.astigmatism, settings.astigmatism_angle_deg)
        if key not in self._stacks:
            pixel = settings.pixel_um
            field_um = pixel * max(settings.rows, settings.cols)
            # Room for start offsets of a quarter field, stage travel and drift.
            if self.sample_image is not None:
                sample = self.sample_image.rasterize(pixel / 2, self.extent_um or self.sample_image.extent_um(field_um))
            else:
                extent = self.extent_um or max(2.2 * field_um, field_um + 60.0)
                sample = rasterize(self.scene, pixel / 2, extent, self.seed)
            levels = []
            for sigma_px in BLUR_LEVELS_PX:
                sigma_grid = 2 * np.hypot(sigma_px, settings.probe_sigma_px)
                blurred = self._probe(sample.intensity, sigma_grid, settings)
                levels.append(blurred)
            self._stacks = {key: _BlurStack(sample, levels)}  # one magnification at a time
        return self._stacks[key]

    @staticmethod
    def _probe(image: np.ndarray, sigma: float, settings: ScanSettings) -> np.ndarray:
        if settings.astigmatism == 1.0:
            return cv2.GaussianBlur(image, (0, 0), sigma)
        # An elliptical Gaussian: widths sigma * sqrt(ratio) and sigma / sqrt(ratio).
        wide, narrow = sigma * np.sqrt(settings.astigmatism), sigma / np.sqrt(settings.astigmatism)
        half = int(np.ceil(3 * max(wide, narrow)))
        y, x = np.mgrid[-half:half + 1, -half:half + 1].astype(np.float32)
        angle = np.deg2rad(settings.astigmatism_angle_deg)
        u, v = x * np.cos(angle) + y * np.sin(angle), -x * np.sin(angle) + y * np.cos(angle)
        kernel = np.exp(-0.5 * ((u / wide) ** 2 + (v / narrow) ** 2))
        return cv2.filter2D(image, -1, (kernel / kernel.sum()).astype(np.float32), borderType=cv2.BORDER_REFLECT)

    def sample(self, settings: ScanSettings) -> Sample:
        return self._stack(settings).sample

    def render(self, settings: ScanSettings, line_start: list[Pose], line_end: list[Pose],
               rng: np.random.Generator) -> np.ndarray:
        """One frame. ``line_start[i]`` / ``line_end[i]`` are the poses when line i's
        first / last pixel is acquired; poses in between are linear in time."""
        stack = self._stack(settings)
        sample = stack.sample
        rows, cols, pixel = settings.rows, settings.cols, settings.pixel_um

        def column(name):
            return np.array([getattr(p, name) for p in line_start], np.float32)[:, None], \
                np.array([getattr(p, name) for p in line_end], np.float32)[:, None]

        fraction = (np.arange(cols, dtype=np.float32) / max(cols - 1, 1))[None, :]

        def along_line(name):
            start, end = column(name)
            return start + (end - start) * fraction if np.any(start != end) else np.broadcast_to(start, (rows, cols))

        stage_x, stage_y = along_line("x_um"), along_line("y_um")
        theta = np.deg2rad(along_line("rotation_deg"))
        # Image-plane coordinates (um) of every pixel, centred.
        image_x = ((np.arange(cols, dtype=np.float32) - (cols - 1) / 2) * pixel)[None, :]
        image_y = ((np.arange(rows, dtype=np.float32) - (rows - 1) / 2) * pixel)[:, None]
        relative_x, relative_y = image_x - stage_x, image_y - stage_y
        # The tilt cradle: the surface point (u, v) (on the turned sample) goes to
        # R (u, v, -pivot) + (0, 0, pivot), R = R_x(alpha) R_y(beta); the image sees its x
        # and y, so (u, v) follows from the pixel by solving those two rows.
        tilt_x, tilt_y = along_line("tilt_x_deg"), along_line("tilt_y_deg")
        tilted = bool(np.any(tilt_x) or np.any(tilt_y))
        if tilted:
            alpha, beta, lever = np.deg2rad(tilt_x), np.deg2rad(tilt_y), self.pivot_depth_um
            cos_a, sin_a, cos_b, sin_b = np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta)
            surface_u = (relative_x + lever * sin_b) / cos_b
            surface_v = (relative_y - sin_a * sin_b * surface_u - lever * sin_a * cos_b) / cos_a
            surface_depth = -cos_a * sin_b * surface_u + sin_a * surface_v + lever * (1 - cos_a * cos_b)
        else:
            surface_u, surface_v, surface_depth = relative_x, relative_y, 0.0
        # Content moves +x with the stage and turns counter-clockwise as displayed with
        # +rotation, so the sample point seen at an image point is R^-1 (image - stage).
        cos, sin = np.cos(theta), np.sin(theta)
        sample_x = cos * surface_u - sin * surface_v
        sample_y = sin * surface_u + cos * surface_v
        map_x, map_y = sample.to_grid(sample_x, sample_y)
        map_x, map_y = map_x.astype(np.float32), map_y.astype(np.float32)

        # Defocus: the depth of each pixel's point (away from the lens: the tilted
        # surface's, less the feature's height along the normal and the stage's z)
        # against the focus; no dead zone, the blur grows as alpha |depth - focus|.
        height = cv2.remap(sample.height_um, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        if tilted:
            height = height * (cos_a * cos_b)
        depth = surface_depth - height - along_line("z_um")
        defocus = np.abs(depth - settings.working_distance_um)
        sigma_px = self.half_angle(settings) * defocus / pixel
        # Blend the two nearest blur levels linearly in variance: a mixture of two
        # Gaussian kernels has exactly the blended second moment, so the blur grows
        # smoothly (as sqrt(probe^2 + (alpha dz / P)^2)) and the focus peak is round, not
        # a cusp at each level.
        levels_variance = np.square(BLUR_LEVELS_PX)
        position = np.interp(np.square(sigma_px), levels_variance,
                             np.arange(len(BLUR_LEVELS_PX))).astype(np.float32)
        lower = np.floor(position).astype(np.int32)
        weight = position - lower
        intensity = np.zeros((rows, cols), np.float32)
        for level in np.unique(lower):
            for index, blend in ((level, 1 - weight), (min(level + 1, len(BLUR_LEVELS_PX) - 1), weight)):
                selected = (lower == level) * blend
                if not np.any(selected):
                    continue
                sampled = cv2.remap(stack.levels[index], map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
                intensity += sampled * selected

        # Charging: regions the beam dwells on brighten slowly (a coarse map over the sample).
        charge_x = ((sample_x / sample.extent_um + 0.5) * (self.charge.shape[1] - 1)).astype(np.float32)
        charge_y = ((sample_y / sample.extent_um + 0.5) * (self.charge.shape[0] - 1)).astype(np.float32)
        intensity += cv2.remap(self.charge, charge_x, charge_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        self._accumulate_charge(charge_x, charge_y, settings)

        # Electrons: Poisson (normal approximation, variance = mean) plus amplifier noise
        # integrated over the same dwell, in one draw.
        electrons = np.maximum(intensity, 0) * (ELECTRONS_PER_NS * settings.dwell_ns)
        variance = electrons + AMPLIFIER_VARIANCE_PER_NS * settings.dwell_ns
        electrons += np.sqrt(variance) * rng.standard_normal((rows, cols), dtype=np.float32)
        signal = electrons / (ELECTRONS_PER_NS * settings.dwell_ns)
        full_scale = (1 << settings.bit_depth) - 1
        grey = (settings.contrast * signal + settings.brightness) * full_scale
        dtype = np.uint8 if settings.bit_depth <= 8 else np.uint16
        return np.clip(grey, 0, full_scale).astype(dtype)

    def _accumulate_charge(self, charge_x: np.ndarray, charge_y: np.ndarray, settings: ScanSettings) -> None:
        self.charge *= 0.995  # slow discharge between frames
        histogram, _, _ = np.histogram2d(charge_y[::8, ::8].ravel(), charge_x[::8, ::8].ravel(),
                                         bins=self.charge.shape, range=[[0, self.charge.shape[0]], [0, self.charge.shape[1]]])
        dose = histogram / max(histogram.max(), 1.0)
        self.charge += (2e-4 * settings.dwell_ns / 720.0) * dose.astype(np.float32)
        np.clip(self.charge, 0, 0.15, out=self.charge)
