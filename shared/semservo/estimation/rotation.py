"""Rotation about the beam (Marturi et al., section II-B-1, eq. 9-12): the high-pass
log-polar magnitude spectrum, the angular correlation and its peaks, turning an image
about its centre; the reference's side of it, made once (:class:`LogPolarReference`),
and of the refinement on the image itself (:class:`ProbeReferences`, :func:`probe_top`;
the steps in ``MotionEstimator._refine_rotation``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
import pyfftw

from semservo.estimation import _kernels
from semservo.estimation.plans import PLANNING_LOCK
from semservo.estimation.resolutions import FullResolution, HalfResolution
from semservo.estimation.translation import centred_shift

#: Small turns are measured against copies of the reference turned by these angles
#: (degrees), see :meth:`LogPolarReference.angle`.
TURNED_REFERENCE_DEG = (1.5, -1.5, 3.0, -3.0)
#: The angle from the log-polar spectrum is refined by probe turns that move the edge of
#: the image's inscribed circle by this many pixels either way (see
#: ``MotionEstimator._refine_rotation``): about where the correlation has fallen by
#: a measurable amount without leaving its parabolic top.
ROTATION_PROBE_PX = 1.0
#: Turns up to this many probes are refined without turning the frame back: it is fitted
#: straight against reference copies turned by whole probes. Turning the frame back by a
#: small angle with OpenCV's bicubic (or bilinear) kernel turns it by a slightly
#: different angle (the kernel's phase error at small sub-pixel moves: 0.3 degree turned
#: back acted as 0.34), which no probe could correct.
SMALL_TURN_PROBES = 3
#: How many peaks of the log-polar correlation are tried, highest first, when the image
#: shows no correlation top near the highest (see ``MotionEstimator._estimate_with_rotation``).
ANGLE_CANDIDATES = 4
#: Bicubic for the turned images the angle is refined on: bilinear interpolation blurs
#: by an amount that depends on the turn (none at 0 and 90 degrees), which pulled the
#: refined angle towards those (0.05 degree mean error on a sparse scene, 0.008 bicubic).
PROBE_INTERPOLATION = cv2.INTER_CUBIC
#: The rotation's sharpness (see ``MotionEstimator._refine_rotation``) at which its
#: confidence is 1 - 1/e. Real SEM scenes lose 4e-4 to 2e-2 of their correlation when a
#: turn moves the image's edge by a pixel (six images of five instruments, at every
#: dose tried); a rotationally symmetric scene (a disc, a ring) loses under 3e-5, so
#: its angle is refused (confidence under 0.25) rather than guessed.
SHARPNESS_SCALE = 1e-4


#: How the rotation's match (the correlation at the refined angle over the one two noisy
#: views of one scene would reach) maps to a confidence: 0 up to MATCH_FLOOR, 1 - 1/e at
#: MATCH_FLOOR + MATCH_SCALE. At the right angle the match was 0.99-1.02 on six real
#: images turned by up to 20 degrees and moved by up to a quarter of the field, at 200
#: and 1000 electrons per grey level; at a wrong angle that still showed a top (a hole's
#: disc, which looks alike at many turns) 0.74-0.87.
MATCH_FLOOR = 0.88
MATCH_SCALE = 0.02


def confidence_from_match(match: float) -> float:
    """Map the rotation's match to [0, 1]: ``1 - exp(-(match - MATCH_FLOOR) / MATCH_SCALE)``."""
    return float(1.0 - np.exp(-max(match - MATCH_FLOOR, 0.0) / MATCH_SCALE))


#: When several angles were tried, the best one's ``distinct`` (how much more the
#: runner-up misses of a perfect correlation) at which the confidence is 1 - 1/e above 1:
#: a scene that a wrong turn matches almost as well (a field mostly filled by a hole's
#: disc, which looks alike at every turn about its own centre) cannot tell the angle.
DISTINCT_SCALE = 1.0


def confidence_from_distinct(distinct: float) -> float:
    """Map the best angle's distinctness to [0, 1]: ``1 - exp(-(distinct - 1) / DISTINCT_SCALE)``."""
    if not np.isfinite(distinct):
        return 1.0
    return float(1.0 - np.exp(-max(distinct - 1.0, 0.0) / DISTINCT_SCALE))


def confidence_from_sharpness(sharpness: float) -> float:
    """Map the rotation's sharpness to [0, 1]: ``1 - exp(-sharpness / SHARPNESS_SCALE)``."""
    return float(1.0 - np.exp(-max(sharpness, 0.0) / SHARPNESS_SCALE))


def highpass_emphasis(shape: tuple[int, int]) -> np.ndarray:
    """Reddy & Chatterji's high-pass H = (1 - X)(2 - X), X = cos(pi u) cos(pi v), on the
    real-input half plane: it damps the low frequencies that the window and the DC
    dominate, so the log-polar correlation follows the image's structure."""
    rows, cols = shape
    v = np.fft.fftfreq(rows)[:, None]
    u = np.fft.rfftfreq(cols)[None, :]
    x = np.cos(np.pi * u) * np.cos(np.pi * v)
    return ((1 - x) * (2 - x)).astype(np.float32)


@dataclass(frozen=True)
class LogPolarGrid:
    """Where to sample a half-plane spectrum on a log-polar grid (eq. 11).

    Angles span 180 degrees (the magnitude spectrum of a real image is centrally
    symmetric, so that is a full period) from -90 to +90 degrees, i.e. u >= 0 only, which
    the real-input half plane holds. Radii are log-spaced in cycles per pixel, so a
    non-square image is sampled in physical frequency, not in bins. The lowest radii
    are left out: there the window's leakage outweighs the scene.
    """

    map_cols: np.ndarray
    map_rows: np.ndarray
    angles: int

    @classmethod
    def for_shape(cls, shape: tuple[int, int], angles: int = 720, radii: int = 96,
                  min_radius: float = 0.02, max_radius: float = 0.45) -> "LogPolarGrid":
        rows, cols = shape
        theta = np.deg2rad(-90 + 180 * np.arange(angles) / angles)
        rho = np.geomspace(min_radius, max_radius, radii)
        u = rho[:, None] * np.cos(theta)[None, :]
        v = rho[:, None] * np.sin(theta)[None, :]
        # Spectrum rows are fft-shifted so v = 0 sits at row rows // 2.
        return cls(
            map_cols=(u * cols).astype(np.float32),
            map_rows=(v * rows + rows // 2).astype(np.float32),
            angles=angles,
        )


def log_polar_magnitude(spectrum: np.ndarray, emphasis: np.ndarray, grid: LogPolarGrid,
                        workspace: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
    """Emphasized magnitude spectrum compressed by log(1 + x), then resampled on ``grid``
    (radii x angles).

    The logarithm comes first: resampling between DFT bins averages neighbours, and
    where the grid meets bins (along the axes) it averages none, so the noise's share of
    a magnitude has a spread that depends on the angle; the logarithm of such an average
    has a mean that then depends on the angle too (it is concave), a pattern that does
    not turn with the scene and that both images share. On noisy, sparse scenes (a dark
    hole, particles on a dark ground) it pulled the log-polar angle to 0 or 90 degrees
    whatever the turn. Logarithms of the bins themselves all have the same mean, and so
    does any average of them.

    ``workspace`` (spectrum-shaped float32) and ``out`` (radii x angles float32) may be
    given to avoid allocating on the per-frame path."""
    if workspace is None:
        workspace = np.empty(spectrum.shape, np.float32)
    _kernels.magnitude_shifted_into(spectrum, emphasis, workspace)
    # log(1 + x) as OpenCV's vectorized log of 1 + x: numpy's float32 log1p is scalar
    # code here (1.2 ms for 96 x 720 against 0.05 ms).
    workspace += 1.0
    cv2.log(workspace, dst=workspace)
    return cv2.remap(workspace, grid.map_cols, grid.map_rows, interpolation=cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE, dst=out)


def angular_spectrum(log_polar: np.ndarray, plan: pyfftw.FFTW | None = None) -> np.ndarray:
    """FFT along the angle of each radius with the mean (DC) removed: what eq. 12
    correlates. ``plan`` is an FFTW plan for this shape (its buffer is returned)."""
    if plan is None:
        spectrum = np.fft.rfft(log_polar, axis=1)
    else:
        plan.input_array[...] = log_polar
        spectrum = plan()
    spectrum[:, 0] = 0
    return spectrum


@dataclass(frozen=True)
class AngularRefiner:
    """Evaluates a band-limited circular correlation near its peak by a local upsampled
    inverse DFT, in two stages (steps of 0.1, then 0.005 sample), bases built once."""

    angles: int
    coarse_offsets: np.ndarray
    coarse_basis: np.ndarray  # (points, frequencies)
    fine_offsets: np.ndarray
    fine_basis: np.ndarray
    hermitian_weights: np.ndarray
    frequencies: np.ndarray  # 0 .. angles // 2

    @classmethod
    def for_angles(cls, angles: int) -> "AngularRefiner":
        k = np.arange(angles // 2 + 1)
        weights = np.full(k.size, 2.0)
        weights[0] = 1.0
        if angles % 2 == 0:
            weights[-1] = 1.0
        coarse = np.linspace(-1, 1, 21)
        fine = np.linspace(-0.1, 0.1, 41)
        basis = lambda offsets: np.exp(2j * np.pi * np.outer(offsets, k) / angles).astype(np.complex64)  # noqa: E731
        return cls(angles, coarse, basis(coarse), fine, basis(fine), weights, k)

    def peak(self, cross: np.ndarray) -> tuple[float, float]:
        """(sub-sample peak position in [-angles/2, angles/2), peak height) of the
        inverse transform of the normalized 1-D cross spectrum ``cross``."""
        surface = np.fft.irfft(cross, n=self.angles)
        coarse = int(np.argmax(surface))
        k = self.frequencies
        weighted = (self.hermitian_weights * cross).astype(np.complex64)
        at_coarse = weighted * np.exp(2j * np.pi * coarse * k / self.angles).astype(np.complex64)
        first = float(self.coarse_offsets[int(np.argmax((self.coarse_basis @ at_coarse).real))])
        at_first = weighted * np.exp(2j * np.pi * (coarse + first) * k / self.angles).astype(np.complex64)
        second = float(self.fine_offsets[int(np.argmax((self.fine_basis @ at_first).real))])
        best = coarse + first + second
        return centred_shift(best % self.angles, self.angles), float(surface[coarse])


def angular_candidates(cross: np.ndarray, angles: int, count: int) -> list[int]:
    """The ``count`` highest local maxima (sample indices, centred) of the inverse
    transform of the 1-D cross spectrum ``cross``, highest first: where else the
    log-polar correlation says the angle may be."""
    surface = np.fft.irfft(cross, n=angles)
    is_peak = (surface >= np.roll(surface, 1)) & (surface > np.roll(surface, -1))
    peaks = np.flatnonzero(is_peak)
    order = peaks[np.argsort(surface[peaks])[::-1]][:count]
    return [int(centred_shift(int(index), angles)) for index in order]


def rotate_about_centre(image: np.ndarray, angle_deg: float, out: np.ndarray | None = None,
                        interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """Rotate content counter-clockwise as displayed by ``angle_deg`` about
    ((cols - 1) / 2, (rows - 1) / 2), borders reflected; bilinear unless an OpenCV
    ``interpolation`` flag says otherwise."""
    rows, cols = image.shape
    matrix = cv2.getRotationMatrix2D(((cols - 1) / 2, (rows - 1) / 2), angle_deg, 1.0)
    return cv2.warpAffine(image, matrix, (cols, rows), dst=out, flags=interpolation,
                          borderMode=cv2.BORDER_REFLECT)


@dataclass
class LogPolarReference:
    """The reference's side of eq. 9-12, made once: the log-polar grid, the high-pass
    emphasis, the reference's angular spectrum (conjugated) and those of copies turned
    by ``TURNED_REFERENCE_DEG`` with the ramps that move their peaks back, the angular
    FFT plan, and the per-frame buffers. :meth:`angle` measures a frame's turn."""

    grid: LogPolarGrid
    refiner: AngularRefiner
    emphasis: np.ndarray
    plan: pyfftw.FFTW
    reference_conjugate: np.ndarray
    turned_conjugates: np.ndarray
    turned_ramps: np.ndarray
    #: Turns under this are measured again against the turned copies.
    small_turn_below_deg: float
    # Per-frame buffers.
    unit_ramp: np.ndarray
    accumulator: np.ndarray
    cross: np.ndarray
    #: The cross spectrum against the reference itself, kept for :meth:`candidates`.
    first_cross: np.ndarray
    log_magnitude: np.ndarray
    log_polar: np.ndarray

    @classmethod
    def of(cls, full: FullResolution, angles: int, fft_effort: str) -> "LogPolarReference":
        """From the reference's full-resolution spectrum; rotation reads the
        full-resolution spectrum because block averaging folds fine structure back
        (aliasing), and folded energy does not turn with the scene, which pulls small
        angles towards zero."""
        grid = LogPolarGrid.for_shape(full.shape, angles=angles)
        emphasis = highpass_emphasis(full.shape)
        reference_conjugate = np.conj(angular_spectrum(
            log_polar_magnitude(np.conj(full.reference_conjugate), emphasis, grid))).astype(np.complex64)
        # Copies of the reference turned by a known angle, for small turns (see
        # angle); Lanczos, since it is done once.
        turned_conjugates = []
        for turn in TURNED_REFERENCE_DEG:
            turned = rotate_about_centre(full.reference, turn, interpolation=cv2.INTER_LANCZOS4)
            spectrum = full.spectrum(turned, float(turned.mean()))
            turned_conjugates.append(np.conj(angular_spectrum(log_polar_magnitude(spectrum, emphasis, grid))))
        # Each turned comparison peaks at (turn - 0) samples off; these ramps move
        # every peak back onto the true turn, so the four add into one surface.
        frequencies = np.arange(angles // 2 + 1)
        turn_samples = np.asarray(TURNED_REFERENCE_DEG) * angles / 180.0
        with PLANNING_LOCK:  # one plan made at a time in this process (plans.PLANNING_LOCK)
            plan = pyfftw.FFTW(pyfftw.empty_aligned(grid.map_cols.shape, "float32"),
                               pyfftw.empty_aligned((grid.map_cols.shape[0], angles // 2 + 1), "complex64"),
                               axes=(1,), flags=(fft_effort,))
        return cls(
            grid=grid, refiner=AngularRefiner.for_angles(angles), emphasis=emphasis, plan=plan,
            reference_conjugate=reference_conjugate,
            turned_conjugates=np.stack(turned_conjugates).astype(np.complex64),
            turned_ramps=np.exp(2j * np.pi * np.outer(turn_samples, frequencies) / angles).astype(np.complex64),
            small_turn_below_deg=min(map(abs, TURNED_REFERENCE_DEG)) / 2,
            unit_ramp=np.ones((1, angles // 2 + 1), np.complex64),
            accumulator=np.empty(angles // 2 + 1, np.complex64), cross=np.empty(angles // 2 + 1, np.complex64),
            first_cross=np.empty(angles // 2 + 1, np.complex64),
            log_magnitude=np.empty(full.reference_conjugate.shape, np.float32),
            log_polar=np.empty(grid.map_cols.shape, np.float32),
        )

    @property
    def degrees_per_sample(self) -> float:
        """Angles run from -90 (column 0 of the log-polar grid) to +90 degrees with v
        along rows (down), so a counter-clockwise turn as displayed moves the profile
        back: a sample is -180 / angles degrees."""
        return -180.0 / self.grid.angles

    def angle(self, spectrum: np.ndarray, small_turns: bool = True) -> float:
        """Rotation of the content modulo 180 degrees (counter-clockwise as displayed), in
        [-90, 90), from the frame's full-resolution spectrum under the fixed window: eq.
        9-12, the log-polar magnitude spectra differ by a shift along the angle. The
        magnitude spectrum is centrally symmetric, so theta and theta + 180 look alike;
        the translation peak settles which (``MotionEstimator.estimate``).

        Small turns: the DFT samples the magnitude spectrum at the image's own Nyquist
        rate, but a magnitude (like the autocorrelation behind it) has twice the
        bandwidth, so the log-polar resampling between bins is aliased and a
        displacement under one bin reads biased towards zero, like pixel locking in
        particle image velocimetry. Below about 0.3 degree every radius moves less than
        a bin and the whole estimate locks near zero (0.1 degree read 0.007 on exactly
        rotated synthetic images). So a turn under 0.75 degree is measured again against
        copies of the reference turned by +-1.5 and +-3 degrees
        (``TURNED_REFERENCE_DEG``), made once: there each radius moves by a different
        fraction of a bin, the bias averages out over radii, and the mean over opposite
        offsets cancels what is left to first order. The image's log-polar spectrum is
        shared, so this costs one more 1-D correlation against the four turned copies
        at once. Measured over turns from -0.8 to 0.6 degree: mean error 0.054 -> 0.004
        degree on exact synthetic rotations (400 x 400), 0.08 -> 0.02 on real frames at
        moderate noise. ``small_turns=False`` skips that second measurement (for when
        the refinement on the image follows: it is not locked at small turns).
        """
        log_polar = log_polar_magnitude(spectrum, self.emphasis, self.grid, self.log_magnitude, self.log_polar)
        current = angular_spectrum(log_polar, self.plan)
        _kernels.normalized_angular_cross_into(current, self.reference_conjugate[np.newaxis], self.unit_ramp,
                                               self.accumulator, self.cross)
        samples, _ = self.refiner.peak(self.cross)
        angle = samples * self.degrees_per_sample
        self.first_cross[...] = self.cross
        if small_turns and abs(angle) < self.small_turn_below_deg:
            # Against each turned copy, normalized (eq. 12), moved back by its known
            # turn and summed: one surface whose peak is the mean of the four estimates.
            _kernels.normalized_angular_cross_into(current, self.turned_conjugates, self.turned_ramps,
                                                   self.accumulator, self.cross)
            samples, _ = self.refiner.peak(self.cross)
            angle = samples * self.degrees_per_sample
        return float(angle)

    def candidates(self, count: int) -> list[float]:
        """The angles (degrees) of the last frame's ``count`` highest log-polar
        correlation peaks against the reference itself, highest first."""
        return [samples * self.degrees_per_sample
                for samples in angular_candidates(self.first_cross, self.grid.angles, count)]


@dataclass
class ProbeReferences:
    """The refinement on the image (``MotionEstimator._refine_rotation``): the reference
    halved under the full-resolution window (as the fast fit's) and turned by whole
    probes of ``step_deg`` (a probe moves the inscribed circle's edge by
    ``ROTATION_PROBE_PX``), their conjugate spectra made once; and the frame halved
    (``half_image``) and turned back (kept per angle)."""

    step_deg: float
    conjugates: dict[int, np.ndarray]
    #: The same copies halved (2 x 2 means), unwindowed: for windows made per frame
    #: (``MotionEstimator._refine_on_overlap``).
    halved: dict[int, np.ndarray]
    half_image: np.ndarray
    half_turned_back: np.ndarray
    half_turned_back_by: float | None = None
    #: The halved frame's pixel noise variance (a quarter of the frame's).
    half_noise: float = 0.0

    @classmethod
    def of(cls, full: FullResolution, half: HalfResolution) -> "ProbeReferences":
        # The probes turn the reference, not the frame: the frame is fitted against
        # copies of the reference turned by whole probes.
        step_deg = float(np.degrees(ROTATION_PROBE_PX / (min(full.shape) / 2)))
        conjugates = {0: half.fit_reference_conjugate}
        halved = {0: _halved(full.reference, half.shape)}
        if half.factor == 2:
            for probe in range(-SMALL_TURN_PROBES - 1, SMALL_TURN_PROBES + 2):
                if probe == 0:
                    continue
                turned = rotate_about_centre(full.reference, probe * step_deg, interpolation=cv2.INTER_LANCZOS4)
                conjugates[probe] = np.conj(half.apodized_spectrum(turned, full.reference_mean, 0, 0))
                halved[probe] = _halved(turned, half.shape)
        return cls(step_deg=step_deg, conjugates=conjugates, halved=halved,
                   half_image=np.empty(half.shape, np.float32), half_turned_back=np.empty(half.shape, np.float32))

    def load(self, image: np.ndarray, noise_variance: float) -> None:
        """Halve the frame (2 x 2 means) into ``half_image``; ``noise_variance``: its pixel
        noise's, at full resolution."""
        _halved(image, self.half_image.shape, self.half_image)
        self.half_turned_back_by = None
        self.half_noise = noise_variance / 4

    def turned_back(self, angle: float) -> np.ndarray:
        """The halved frame turned back by ``angle`` degrees (bicubic, kept per angle; a
        half turn from the kept angle is the kept image flipped, exactly: the turns are
        about the pixel grid's centre)."""
        if self.half_turned_back_by != angle:
            kept = self.half_turned_back_by
            if kept is not None and abs((angle - kept) % 360.0 - 180.0) < 1e-9:
                self.half_turned_back[...] = self.half_turned_back[::-1, ::-1].copy()
            else:
                rotate_about_centre(self.half_image, -angle, self.half_turned_back, PROBE_INTERPOLATION)
            self.half_turned_back_by = angle
        return self.half_turned_back


def _halved(image: np.ndarray, shape: tuple[int, int], out: np.ndarray | None = None) -> np.ndarray:
    """``image`` resized to ``shape`` by area averaging (2 x 2 means when halved)."""
    return cv2.resize(image, shape[::-1], dst=out, interpolation=cv2.INTER_AREA)


def moved(image: np.ndarray, row_shift: int, col_shift: int) -> np.ndarray:
    """``image`` moved by whole pixels: out[y, x] = image[y - row_shift, x - col_shift],
    zero where that falls outside."""
    rows, cols = image.shape
    out = np.zeros_like(image)
    if abs(row_shift) < rows and abs(col_shift) < cols:
        out[max(row_shift, 0):rows + min(row_shift, 0), max(col_shift, 0):cols + min(col_shift, 0)] = \
            image[max(-row_shift, 0):rows + min(-row_shift, 0), max(-col_shift, 0):cols + min(-col_shift, 0)]
    return out


def visible_window(window: np.ndarray, turned_back_deg: float) -> np.ndarray:
    """``window`` as a frame turned back by ``turned_back_deg`` (about its centre) carries
    it: zero where the turned-back frame has no data. A symmetric window's is the same
    for a turn and that turn plus a half turn."""
    if not turned_back_deg:
        return window
    rows, cols = window.shape
    matrix = cv2.getRotationMatrix2D(((cols - 1) / 2, (rows - 1) / 2), -turned_back_deg, 1.0)
    return cv2.warpAffine(window, matrix, (cols, rows), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=0)


class OverlapWindows(NamedTuple):
    """Windows that weight the same scene in the reference and in a frame that shows it
    moved (:func:`overlap_windows`), and the reference window's centroid (x, y), in
    pixels from the image's centre."""

    reference: np.ndarray
    frame: np.ndarray
    centroid: tuple[float, float]


def overlap_windows(window: np.ndarray, turned_back_deg: float, shift: tuple[float, float],
                    visible: np.ndarray | None = None) -> OverlapWindows:
    """The windows under which a reference and a frame showing its content moved by
    ``shift`` (dy, dx; the frame turned back by ``turned_back_deg`` about its centre
    first) weight the same scene the same way.

    A frame far from the reference shares only part of its field: the window moved with
    the content then runs off the frame's edge (a hard cut while the window still
    weighs), and the reference keeps, at full weight, what the frame does not show.
    Both bias a correlation over turns (the cut is a straight edge, which turned copies
    of the reference match differently, and the unshared content correlates by chance).
    So both images are weighted by the product of the two windows carried onto each:
    the reference's point q by window(q) x visible(q + shift), the frame's point p by the
    same, window(p - shift) x visible(p), where ``visible`` is the frame's own window
    (turned back with it: zero where the turned-back frame has no data; it may be given,
    made by :func:`visible_window`). Both taper to zero inside the overlap, so neither
    has a hard edge.
    """
    if visible is None:
        visible = visible_window(window, turned_back_deg)
    row_shift, col_shift = int(round(shift[0])), int(round(shift[1]))
    reference = window * moved(visible, -row_shift, -col_shift)
    total = float(reference.sum())
    rows, cols = reference.shape
    if total > 0:
        centroid = (float((reference.sum(axis=0) * np.arange(cols)).sum() / total - (cols - 1) / 2),
                    float((reference.sum(axis=1) * np.arange(rows)).sum() / total - (rows - 1) / 2))
    else:
        centroid = (0.0, 0.0)
    return OverlapWindows(reference, moved(reference, row_shift, col_shift), centroid)


class ProbeTop(NamedTuple):
    """The top of a parabola through three probes' correlations: where it lies (in
    probes from the middle one), how sharp it is (the fraction of the correlation lost
    one probe away) and how high (the correlation there)."""

    offset: float
    sharpness: float
    height: float


#: A correlation that falls by more than this fraction one probe from its top is not a
#: top but fits that broke down (real scenes lose 4e-4 to 2e-2, see SHARPNESS_SCALE).
MAX_SHARPNESS = 0.1


def probe_top(below: float, at: float, above: float) -> ProbeTop | None:
    """The parabola through the correlations one probe below, at and one above the
    middle probe; None when the middle is not a top (no curvature, or a neighbour is
    higher): the image cannot tell the angle there; None too when it falls by more than
    ``MAX_SHARPNESS`` a probe. The height is never above the middle's own."""
    curvature = below - 2 * at + above
    if curvature >= 0 or at < max(below, above):
        return None
    offset = 0.5 * (below - above) / curvature
    top = at - 0.125 * (below - above) ** 2 / curvature
    sharpness = -0.5 * curvature / top if top > 0 else 0.0
    if sharpness > MAX_SHARPNESS:
        return None
    return ProbeTop(offset, sharpness, min(top, at + 0.5 * abs(below - above)))
