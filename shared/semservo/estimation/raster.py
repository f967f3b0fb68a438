"""The shift averaged over a scan's time: what a raster frame's vibration hides.

An SEM scans a frame row after row, so each band of rows is a snapshot of the sample at
its own time. Stage vibration faster than a frame (at x5000 the simulated lab's 10 nm at
7 Hz is 0.24 px; 50 Hz mains pick-up does the same on real instruments) moves the
content between bands: the frame is the scene drawn with wavy rows. A correlation of
the whole frame (eq. 18-24) measures the shift its texture sees, weighting each band by
how much edge it holds, so one frame's estimate scatters about where the sample rested
by a good part of the vibration's amplitude (0.1 px at x5000, where the mean of the
vibration over the frame's scan is 0.02 px).

:func:`scan_averaged_shift` measures each band of rows on its own, by one Lucas-Kanade
step about the whole-frame estimate (the reference, smoothed, turned and moved by that
estimate, predicts the frame; each band's least-squares residue, with its own gain and
offset for the detector's levels, gives that band's shift), and averages the bands with
random-effects weights (:func:`random_effects_mean`): nearly uniform, as the scan's time
is, where the vibration moves the bands apart more than their noise; the bands' inverse
variances where it does not.

Measured (``./dev bench scan_averaged``; the simulated lab, 10 seeds x 10 frames at rest,
against the simulator's pose averaged over each scan): at x5000 the error's RMS falls
from 0.090 to 0.051 px (0.07-0.11 to 0.024-0.068 px per seed, but for one seed at 0.10
either way: its scene is two long parallel edges, so each band pins only the shift
across them and, along them, only the bands with the hole and the dots do: there the
average is the texture's again), at x1200 from 0.007 to 0.006 px. In the closed loop at
x5000 (the position law, the 40 timed starts of ``./dev bench time_to_target``) the
fresh frames fall from a median of 11.5 to 5.5 and a worst of 33 to 31, the true final
error's worst from 0.188 to 0.154 px, 40/40 converged either way. Frames distorted
another way (a band-limited texture sampled row by row at a sinusoidally moving
position, ``tests/unit/test_raster.py``): 0.05-0.25 px to 0.006-0.025 px. The real drift
pair (no truth) closes A -> B -> A to 0.000 px either way; the 2013 run's 54 frames
differ between the two by 0.017 px (median), 0.08 at most. The other presets' closed
loops (``--closed-loop-presets``) tie: a median of 4-4.5 fresh frames and a worst of 7
either way, the worst true final error 0.064-0.072 px against 0.063-0.082 (the mask
reference is never scan-averaged). Through the whole stack (``./dev bench positioning``)
x5000 took 5.9 iterations instead of 9.2, its worst true final error 0.120 px instead of
0.168, the other presets tied; the paper's law at x5000 took 45.5 fresh frames instead of
47. The estimator service uses it by default (``SEMSERVO_ESTIMATOR__SCAN_AVERAGED``); the
library only when asked.

What is left at x5000 is the vibration within a band: 50 and 93 Hz move a band's 32 rows
apart too, so each band's shift is 0.14 px RMS from its true mean pose (narrower bands
measured each worse: 0.059 px RMS over the frame with 8 rows, 0.057 with 16), and the
bands without edges, left out, take their moment of the vibration with them.

Vibration lines. A stage's vibration is mostly a few steady tones (building modes,
pumps, mains pick-up), so a frame's rows are a mean pose plus a few sinusoids in the
rows' time. :func:`vibration_lines` learns their frequencies from frames at rest (a
greedy line search on the Lucas-Kanade step's normal equations summed per row,
:func:`row_sums`; each line kept only above what noise gives over the whole search), and
:func:`line_model_fit` fits, in each frame, the mean and each line's phase and amplitude
on every row with edges, the lines centred on the rows' mean: the mean is then the
scan's time average, the rows without edges filled by the lines rather than left out.
The estimator service learns them at each teach from the frames scanned after the stage
settled (``SEMSERVO_ESTIMATOR__VIBRATION_LINES``, on by default), the timed trials at
theirs. On the simulated lab at x5000 (``./dev bench scan_averaged --wander``, 10 labs x
10 frames at rest) the error falls from 0.051 px RMS (0.025-0.099 per lab, the bands'
mean) to 0.012 (0.006-0.029), learning 7, 50 and 93 Hz in every lab (within 0.05 Hz).
The lines' fit assumes tones: with the simulator's tones wandering 0.3 and 1 radian a
scan it still beats the bands' mean there (0.020 and 0.036 against 0.053 and 0.059),
since that scene's bands without edges lose their moment whatever the vibration; on
frames made another way with edges in every band (``tests/unit/test_raster.py``, a
texture resampled row by row) it beats the bands' mean while each line's phase wanders
up to ~0.3 radian a scan (0.011 against 0.023 px), ties at ~0.6 and is worse at ~1
radian a scan (0.036 against 0.023): there, switch it off.

The turn. The wavy rows are a shear, and a whole-frame turn reads it wherever the texture
spans few of the frame's rows (particles in a corner). :func:`row_waves` gives each row's
displacement by the lines fitted in a frame, :func:`dewaved` moves the rows back by it,
and the estimator measures such frames again with ``steady_rows=True``
(``MotionEstimator._steadied``; not the estimator service's: worse on one picture through
the whole stack): on the
drift pair at rest the turn's error falls from 0.039 to 0.007 degree RMS, and the shift
at the frame's centre, carried from the texture through the turn, from 0.11-0.14 to
0.03-0.05 px (README, "The turn on the rows moved back").

A band that cannot pin its shift (no edges across it, or outside the scene both images
share) is left out; a frame where fewer than half the bands can is left with its
whole-frame estimate, as is one whose bands disagree with it by more than a pixel (the
step is linear: it only refines an estimate already close).

Pure functions on arrays; :class:`semservo.estimation.MotionEstimator` calls them with
``scan_averaged=True`` (``semservo estimate --scan-averaged``; the estimator service's
``SEMSERVO_ESTIMATOR__SCAN_AVERAGED=true``).
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple, Sequence

import cv2
import numpy as np


#: Rows per band: 32 rows are 10-30 ms of scan at the paper's dwell times, shorter than a
#: period of the vibration a frame cannot average (a few to tens of Hz), and enough
#: edge for a band's shift to be known to a few hundredths of a pixel.
BAND_ROWS = 32

#: Both images are low-passed by a Gaussian of this width (px) before their gradients
#: are taken, so the gradients follow the scene and not the pixel noise.
SMOOTHING_PX = 1.5

#: Pixels from either image's border left out: the smoothing's reach (3 widths) and the
#: gradients' one pixel.
EDGE_PX = int(np.ceil(3 * SMOOTHING_PX)) + 1

#: Pixels per independent noise sample after that smoothing: white noise low-passed by
#: a Gaussian of width s is correlated over an area of 4 pi s^2.
NOISE_CORRELATION_AREA = 4 * np.pi * SMOOTHING_PX ** 2

#: The bands' least squares use every second row and column: the smoothed images'
#: neighbouring pixels carry nearly the same information (their noise is alike over
#: 4 pi s^2 = 28 px), so the estimate is all but the same (x5000 at rest: 0.0545 px RMS
#: against 0.0539 from every pixel; x1200: 0.0060 against 0.0059) at half the cost (the
#: whole refinement 4.5 ms a 512 x 512 frame instead of 8).
SAMPLE_STEP = 2

#: A band whose shift is known worse than this (px, one standard deviation on its worse
#: axis, from the residue's own scatter) is left out of the average.
BAND_UNCERTAINTY_PX = 0.5

#: Frames scanned faster than this (s) are left with their whole-frame estimate: the
#: vibrations that move a stage (building and mechanical, 5-100 Hz; mains pick-up at 50
#: or 60 Hz) hardly move the rows of so short a frame apart, while the refinement (about
#: 4.5 ms a 512 x 512 frame) would double the loop's latency at the frame rates where it
#: counts (a replay at 100 frames/s and more, where the loop keeps its p99 under 10 ms).
#: SEM frames at high magnification take 0.1-10 s.
SCAN_AVERAGED_FROM_S = 0.025


#: A partial frame (the rows of a scan scanned after a move settled) is measured, and
#: acted on, when it holds at least this fraction of the scan's rows: half a frame still
#: shares half the field with the reference, and a move written soon after a frame lands
#: early in the next scan, leaving most of it (a 50 ms decision and 10-30 ms of settling:
#: 80-85 % of a 0.3-0.46 s scan).
PARTIAL_FRAME_FROM = 0.5


def band_start(row: int) -> int:
    """``row`` rounded up to the start of a band of :data:`BAND_ROWS` (where a partial
    frame's rows begin: the scan-averaged shift measures whole bands)."""
    return -(-int(row) // BAND_ROWS) * BAND_ROWS


def rows_scanned_after(rows: int, scan_start: float, scan_end: float, after: float, *,
                       min_fraction: float = PARTIAL_FRAME_FROM) -> int | None:
    """The first row, at the start of a band of :data:`BAND_ROWS`, of a frame scanned
    from ``scan_start`` to ``scan_end`` (rows at a constant pace, one clock for all three
    times) whose rows were all scanned at or after ``after``: the partial frame of a scan
    that a move settled in. 0 when the whole scan began after it; None when the scan ended
    before it, its times are unknown or out of order, or fewer than ``min_fraction`` of
    the rows are left."""
    if scan_start is None or scan_end is None or not scan_end > scan_start or rows <= 0:
        return None
    if after <= scan_start:
        return 0
    if after >= scan_end:
        return None
    line = (scan_end - scan_start) / rows
    first = band_start(math.ceil((after - scan_start) / line - 1e-9))
    return first if rows - first >= min_fraction * rows else None


def scan_lasted_s(shape: tuple[int, int], *, source_interval_s: tuple[float, float] | None = None,
                  dwell_ns: float | None = None, scan_started_at_ns: int | None = None,
                  acquired_at_ns: int | None = None, previous_acquired_at_ns: int | None = None) -> float | None:
    """How long a frame's scan lasted (s), from what its header says: its scan's start and
    end on the source's own clock (a simulated lab's time, however fast it runs), else
    its dwell time over its pixels, else its scan's start and end in Unix time, else at
    most the time since the frame before it (a source that scans continuously cannot
    take longer); None if nothing says."""
    if source_interval_s is not None and source_interval_s[1] > source_interval_s[0]:
        return float(source_interval_s[1] - source_interval_s[0])
    if dwell_ns:
        return dwell_ns * 1e-9 * shape[0] * shape[1]
    if scan_started_at_ns is not None and acquired_at_ns is not None and acquired_at_ns > scan_started_at_ns:
        return (acquired_at_ns - scan_started_at_ns) / 1e9
    if previous_acquired_at_ns is not None and acquired_at_ns is not None and acquired_at_ns > previous_acquired_at_ns:
        return (acquired_at_ns - previous_acquired_at_ns) / 1e9
    return None


#: Corrections larger than this (px) mean the whole-frame estimate was not close enough
#: for one linear step: the whole-frame estimate is kept.
MAX_CORRECTION_PX = 1.0


class ScanAveragedShift(NamedTuple):
    """The shift averaged over the scan's bands of rows (:func:`random_effects_mean`), and
    what it came from."""

    dx: float
    dy: float
    #: Each band's shift (x, y, px) at its first row, NaN where the band was left out.
    band_shifts: np.ndarray
    band_first_rows: np.ndarray
    #: How many bands the average is over.
    bands_used: int
    #: The vibration lines' fit the mean came from (:func:`row_waves` gives the frame's
    #: wavy rows from it, :func:`dewaved` undoes them); None: the bands' mean.
    line_fit: LineFit | None = None


def smoothed(image: np.ndarray) -> np.ndarray:
    """``image`` as float32 low-passed by the Gaussian of :data:`SMOOTHING_PX`."""
    return cv2.GaussianBlur(np.asarray(image, np.float32), (0, 0), SMOOTHING_PX, borderType=cv2.BORDER_REFLECT)


class ScanReference(NamedTuple):
    """A reference made ready for :func:`scan_averaged_shift`, once: smoothed, and the
    smoothed image's spectrum (moving it by a fraction of a pixel is then one inverse FFT)."""

    smoothed: np.ndarray
    spectrum: np.ndarray

    @classmethod
    def of(cls, reference: np.ndarray) -> "ScanReference":
        image = smoothed(reference)
        return cls(image, np.fft.rfft2(image))


def _moved(spectrum: np.ndarray, shape: tuple[int, int], dx: float, dy: float) -> np.ndarray:
    """The image of ``spectrum`` moved by (``dx``, ``dy``) px, content wrapping around:
    exact for a band-limited image (an interpolating warp errs by up to a few hundredths
    of a pixel depending on the fraction, which the step would read as the frame's)."""
    rows, cols = shape
    ramp_y = np.exp(-2j * np.pi * np.fft.fftfreq(rows) * dy)
    ramp_x = np.exp(-2j * np.pi * np.fft.rfftfreq(cols) * dx)
    return np.fft.irfft2(spectrum * ramp_y[:, None] * ramp_x[None, :], s=shape).astype(np.float32)


def predicted_frame(reference: ScanReference, dx: float, dy: float, rotation_deg: float = 0.0
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The reference turned by ``rotation_deg`` about the image centre and moved by
    (``dx``, ``dy``): the frame the motion estimate predicts (the sign convention of
    :mod:`semservo.estimation`), and where it is known (a boolean map: pixels whose
    source lies inside the reference, both :data:`EDGE_PX` from a border)."""
    shape = rows, cols = reference.smoothed.shape
    spectrum = reference.spectrum
    if rotation_deg != 0.0:
        # Imported here: the rotation module loads numba and FFTW, and the controller and
        # the gateway import this module for its constants alone.
        from semservo.estimation.rotation import rotate_about_centre

        spectrum = np.fft.rfft2(rotate_about_centre(reference.smoothed, rotation_deg, interpolation=cv2.INTER_CUBIC))
    predicted = _moved(spectrum, shape, dx, dy)
    # Within the smoothing's reach of either image's border, the smoothing saw the border's
    # reflection in one image and the scene in the other: a residue that reads as a shift
    # (0.2 px in the dark bands of the real drift pair).
    edge = EDGE_PX
    inside = np.zeros(shape, np.uint8)
    inside[edge:-edge, edge:-edge] = 1
    # The same turn as rotate_about_centre, then the move.
    turn = cv2.getRotationMatrix2D(((cols - 1) / 2, (rows - 1) / 2), rotation_deg, 1.0)
    turn[:, 2] += (dx, dy)
    known = cv2.warpAffine(inside, turn, (cols, rows), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                           borderValue=0)
    known[:edge], known[-edge:], known[:, :edge], known[:, -edge:] = 0, 0, 0, 0
    return predicted, known.astype(bool)


class RowSums(NamedTuple):
    """The Lucas-Kanade step's normal equations summed per sampled row (:func:`row_sums`):
    for the design's columns (content shift x, y; gain; offset) their products' sums
    ``normal`` (rows x 4 x 4) and their sums against the residue ``moments`` (rows x 4),
    the residue's squares, the known pixels counted, and which row of the frame each is."""

    normal: np.ndarray
    moments: np.ndarray
    target_squares: np.ndarray
    counts: np.ndarray
    rows: np.ndarray


def row_sums(smoothed_frame: np.ndarray, predicted: np.ndarray, known: np.ndarray) -> RowSums:
    """The normal equations of ``frame - predicted = -grad(predicted) . shift + gain *
    predicted + offset`` over each sampled row's known pixels (every
    :data:`SAMPLE_STEP`-th row and column): what both the bands' shifts
    (:func:`band_shifts`) and the vibration lines' fit (:func:`line_model_fit`) sum."""
    grad_y, grad_x = np.gradient(predicted)
    # Content moved by s: frame(p) = predicted(p - s) ~ predicted(p) - grad . s. The
    # design's columns, zero where the pixel is not known.
    sampled = (slice(0, None, SAMPLE_STEP), slice(0, None, SAMPLE_STEP))
    inside = known[sampled].astype(np.float32)
    target = (smoothed_frame[sampled] - predicted[sampled]) * inside
    columns = (-grad_x[sampled] * inside, -grad_y[sampled] * inside, predicted[sampled] * inside, inside)
    normal = np.empty((target.shape[0], 4, 4))
    for i in range(4):
        for j in range(i, 4):
            normal[:, i, j] = normal[:, j, i] = (columns[i] * columns[j]).sum(axis=1, dtype=np.float64)
    moments = np.stack([(column * target).sum(axis=1, dtype=np.float64) for column in columns], axis=1)
    return RowSums(normal, moments, (target * target).sum(axis=1, dtype=np.float64),
                   inside.sum(axis=1, dtype=np.float64), np.arange(0, predicted.shape[0], SAMPLE_STEP))


#: The residues are worth one independent sample per correlation area of the smoothed
#: noise (4 pi s^2), counted in samples.
CORRELATION_SAMPLES = max(NOISE_CORRELATION_AREA / SAMPLE_STEP**2, 1.0)


def band_shifts(smoothed_frame: np.ndarray, predicted: np.ndarray, known: np.ndarray,
                band_rows: int = BAND_ROWS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each band's shift beyond the prediction, by one Lucas-Kanade step with its own
    gain and offset: the least-squares (shift x, shift y, gain, offset) of
    ``frame - predicted = -grad(predicted) . shift + gain * predicted + offset`` over the
    band's known pixels. Returns the shifts (bands x 2, px), their standard deviations
    (bands x 2, px, from the residue's scatter; inf where the band cannot pin them) and
    each band's first row."""
    return band_shifts_of(row_sums(smoothed_frame, predicted, known), predicted.shape[0], band_rows)


def band_shifts_of(sums: RowSums, rows: int, band_rows: int = BAND_ROWS
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`band_shifts` from a frame's :func:`row_sums` (``rows``: the frame's)."""
    first_rows = np.arange(0, rows - band_rows // 2, band_rows)

    def per_band(values: np.ndarray) -> np.ndarray:
        return np.add.reduceat(values, first_rows // SAMPLE_STEP)

    normal, moments = per_band(sums.normal), per_band(sums.moments)
    target_squares, counts = per_band(sums.target_squares), per_band(sums.counts)
    shifts = np.full((len(first_rows), 2), np.nan)
    spreads = np.full((len(first_rows), 2), np.inf)
    for index, count in enumerate(counts):
        if count * SAMPLE_STEP**2 < 8 * band_rows:
            continue
        try:
            covariance = np.linalg.inv(normal[index])
        except np.linalg.LinAlgError:
            continue
        solution = covariance @ moments[index]
        # The least-squares residue |t|^2 - 2 x.b + x.N.x, with N x = b; never below the
        # images' own float32 rounding (identical frames: a band without edges would
        # otherwise look certain of its shift by the rounding of the sums).
        level_squared = normal[index, 2, 2] / count  # the predicted band's mean square
        scatter = max(float(target_squares[index] - solution @ moments[index]) / max(count - 4, 1),
                      float(np.finfo(np.float32).eps) ** 2 * level_squared)
        variance = np.diag(covariance)[:2] * scatter * CORRELATION_SAMPLES
        if not np.all(np.isfinite(solution)) or not np.all(variance > 0):
            continue
        shifts[index] = solution[:2]
        spreads[index] = np.sqrt(variance)
    return shifts, spreads, first_rows


def random_effects_mean(estimates: np.ndarray, variances: np.ndarray) -> float:
    """The mean of the bands' true shifts from their estimates and noise variances, by
    DerSimonian and Laird's random-effects weights 1 / (variance + tau^2), tau^2 the
    spread of the true shifts between bands beyond the noise (moment estimate): where
    vibration moves the bands apart far more than their noise, the weights are nearly
    uniform (the scan's time average); where it does not, they are the bands' inverse
    variances (the texture's weighting, as the whole frame's correlation, with its lower
    noise). Nothing to tune."""
    weights = 1.0 / variances
    fixed = float(np.sum(weights * estimates) / np.sum(weights))
    heterogeneity = float(np.sum(weights * (estimates - fixed) ** 2))
    scale = float(np.sum(weights) - np.sum(weights ** 2) / np.sum(weights))
    between = max(0.0, (heterogeneity - (len(estimates) - 1)) / scale) if scale > 0 else 0.0
    weights = 1.0 / (variances + between)
    return float(np.sum(weights * estimates) / np.sum(weights))


def scan_averaged_shift(reference: ScanReference, frame: np.ndarray, dx: float, dy: float,
                        rotation_deg: float = 0.0, band_rows: int = BAND_ROWS, *,
                        lines_hz: tuple[float, ...] = (), line_time_s: float | None = None
                        ) -> ScanAveragedShift | None:
    """The shift of ``frame`` against the reference averaged over the scan's bands of rows
    per axis by :func:`random_effects_mean` (module docstring), refining the whole-frame estimate (``dx``, ``dy``,
    ``rotation_deg``); None where it cannot (fewer than half the bands pin their shift,
    or the bands' mean moves the estimate by more than :data:`MAX_CORRECTION_PX`).

    With the stage's vibration lines (``lines_hz``, learned by :func:`vibration_lines`)
    and the scan's time per row (``line_time_s``), the mean is instead the scan's time
    average of a displacement that is a mean plus those lines (:func:`line_model_fit`):
    each line's phase and amplitude in this frame are fitted on every row that has edges,
    so the rows without edges no longer weigh the mean towards the ones with.

    ``reference``: :meth:`ScanReference.of` the reference (made once per reference);
    ``frame``: the frame as it came.
    """
    predicted, known = predicted_frame(reference, dx, dy, rotation_deg)
    sums = row_sums(smoothed(frame), predicted, known)
    shifts, spreads, first_rows = band_shifts_of(sums, predicted.shape[0], band_rows)
    usable = np.all(spreads <= BAND_UNCERTAINTY_PX, axis=1)
    if usable.sum() * 2 < len(first_rows):
        return None
    fit = line_model_fit(sums, line_time_s, lines_hz, band_rows) if lines_hz and line_time_s and line_time_s > 0 \
        else None
    if fit is not None and np.all(np.isfinite(fit.mean)) and float(np.hypot(*fit.mean)) <= MAX_CORRECTION_PX:
        correction = fit.mean
    else:  # no lines, or the rows cannot pin them: the bands' mean
        fit = None
        correction = np.array([random_effects_mean(shifts[usable, axis], spreads[usable, axis] ** 2)
                               for axis in range(2)])
    if not np.all(np.isfinite(correction)) or float(np.hypot(*correction)) > MAX_CORRECTION_PX:
        return None
    shifts[~usable] = np.nan
    return ScanAveragedShift(dx + float(correction[0]), dy + float(correction[1]), shifts, first_rows,
                             int(usable.sum()), fit)


# --------------------------------------------------------------------------------------
# Vibration lines: a stage's vibration is mostly a few steady tones (building modes,
# pumps, mains pick-up at 50 or 60 Hz), so a frame's wavy rows are a mean pose plus a
# few sinusoids of known frequency, whose phase and amplitude each frame fits.

#: The most vibration lines :func:`vibration_lines` learns.
MAX_VIBRATION_LINES = 4
#: A line is learned only if the frames' fit improves by more than chance would allow
#: with this probability over the whole search (all frequencies tried: Bonferroni).
LINE_FALSE_ALARM = 1e-3
#: Frequencies tried per the scan's own resolution (1 / the scan's time).
LINE_OVERSAMPLING = 4


class LineFit(NamedTuple):
    """A frame's displacement beyond the prediction as a mean plus vibration lines
    (:func:`line_model_fit`): the mean over the scan's rows (x, y px), and how much of the
    residue the model explains (in units of the residue's noise variance; what
    :func:`vibration_lines` compares models by); and each line's cosine and sine
    coefficients per axis (2 x 2 lines, px)."""

    mean: np.ndarray
    explained: float
    noise_variance: float
    waves: np.ndarray | None = None


def row_waves(fit: LineFit, rows: int, line_time_s: float, lines_hz: Sequence[float]) -> np.ndarray | None:
    """Each of a frame's ``rows`` displaced by the fitted lines beyond the mean (rows x 2:
    x, y px), the lines centred on the rows' mean as :func:`line_model_fit` fits them;
    None without lines."""
    if fit.waves is None or not len(lines_hz):
        return None
    basis = _line_basis(np.arange(rows), line_time_s, lines_hz)[:, 1:]
    return (basis @ fit.waves.T).astype(np.float64)


def dewaved(frame: np.ndarray, waves: np.ndarray) -> np.ndarray:
    """``frame`` with each row's content moved back by its displacement ``waves`` (rows x
    2, px: :func:`row_waves`): the scene as at the scan's mean pose, without the wavy rows
    the vibration drew (float32; cubic, mirrored at the edges).

    Why: a whole-frame turn reads the wavy rows' shear as a turn wherever the texture does
    not span the frame's rows. On the drift pair (particles in one corner) the simulated
    lab's 10 nm at 7 Hz turned it by 0.039 degree RMS a frame (0.004 without vibration),
    which the lever to the frame's centre (about 240 px) carried into x, y as 0.1-0.26 px."""
    rows, cols = frame.shape
    grid_x, grid_y = np.meshgrid(np.arange(cols, dtype=np.float32), np.arange(rows, dtype=np.float32))
    # Content moved by s: frame(p) = scene(p - s), so the scene is frame(p + s).
    return cv2.remap(np.asarray(frame, dtype=np.float32), grid_x + waves[:, 0, None].astype(np.float32),
                     grid_y + waves[:, 1, None].astype(np.float32), cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)


def _line_basis(rows: np.ndarray, line_time_s: float, lines_hz: Sequence[float]) -> np.ndarray:
    """rows x (1 + 2 lines): a constant, then each line's cosine and sine over the rows'
    times, centred on the rows' mean (so the constant's coefficient is the mean)."""
    time = rows.astype(np.float64) * line_time_s
    basis = [np.ones_like(time)]
    for frequency in lines_hz:
        for wave in (np.cos(2 * np.pi * frequency * time), np.sin(2 * np.pi * frequency * time)):
            basis.append(wave - wave.mean())
    return np.stack(basis, axis=1)


def _line_systems(sums: RowSums, bases: np.ndarray, band_rows: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The normal equations of :func:`line_model_fit` for a batch of bases (models x rows
    x K): matrices (models x P x P), right-hand sides (models x P), the parameters P
    being per axis K terms, then each band's gain and offset (bands no known pixel
    reaches left out), and K. Sums over rows as matrix products."""
    models, rows_count, terms = bases.shape
    bands = ((sums.rows - sums.rows[0]) // band_rows).astype(int)
    starts = np.flatnonzero(np.r_[True, bands[1:] != bands[:-1]])  # each band's first sampled row
    band_count = len(starts)
    normal, moments = sums.normal, sums.moments
    pairs = (bases[:, :, :, None] * bases[:, :, None, :]).reshape(models, rows_count, terms * terms)
    shift_block = np.matmul(pairs.transpose(0, 2, 1), normal[:, :2, :2].reshape(rows_count, 4))
    shift_block = shift_block.reshape(models, terms, terms, 2, 2).transpose(0, 3, 1, 4, 2)
    shift_block = shift_block.reshape(models, 2 * terms, 2 * terms)
    cross = np.add.reduceat(bases[:, :, :, None, None] * normal[None, :, None, :2, 2:], starts, axis=1)
    cross = cross.transpose(0, 3, 2, 4, 1).reshape(models, 2 * terms, 2 * band_count)
    per_band = np.add.reduceat(normal[:, 2:, 2:], starts)  # bands x 2 x 2
    levels = np.zeros((2, band_count, 2, band_count))
    for c in range(2):
        for d in range(2):
            levels[c, np.arange(band_count), d, np.arange(band_count)] = per_band[:, c, d]
    levels = np.broadcast_to(levels.reshape(2 * band_count, 2 * band_count), (models, 2 * band_count, 2 * band_count))
    matrices = np.concatenate([np.concatenate([shift_block, cross], axis=2),
                               np.concatenate([cross.transpose(0, 2, 1), levels], axis=2)], axis=1)
    shift_moments = np.matmul(bases.transpose(0, 2, 1), moments[:, :2]).transpose(0, 2, 1).reshape(models, -1)
    level_moments = np.broadcast_to(np.add.reduceat(moments[:, 2:], starts).T.reshape(-1), (models, 2 * band_count))
    vectors = np.concatenate([shift_moments, level_moments], axis=1)
    used = np.concatenate([np.ones(2 * terms, bool), np.tile(per_band[:, 1, 1] > 0, 2)])
    return matrices[:, used][:, :, used], vectors[:, used], terms


def _noise_variance(sums: RowSums, explained_squares: float, parameters: int) -> float:
    """The residue's variance per independent sample (as :func:`band_shifts`), never
    below the images' own float32 rounding."""
    count = float(sums.counts.sum())
    level_squared = float(np.sum(sums.normal[:, 2, 2])) / count
    return max((float(sums.target_squares.sum()) - explained_squares) / (count - parameters),
               float(np.finfo(np.float32).eps) ** 2 * level_squared) * CORRELATION_SAMPLES


def line_model_fit(sums: RowSums, line_time_s: float, lines_hz: Sequence[float], band_rows: int = BAND_ROWS,
                   noise_variance: float | None = None) -> LineFit | None:
    """One Lucas-Kanade step (the design of :func:`row_sums`) whose content shift at row
    r, scanned at t = r x ``line_time_s``, is d(t) = m + sum over the lines f of a_f
    cos(2 pi f t) + b_f sin(2 pi f t), per axis, with each band of ``band_rows`` its own
    gain and offset (the detector's levels); the sinusoids are centred on the rows'
    mean, so m is the displacement averaged over the scan's time, which is what a frame's
    pose is. None when the rows cannot pin the model (too few with edges).

    The noise variance is the residue's (as :func:`band_shifts`, per independent
    sample), unless given (to compare models on one scale)."""
    matrices, vectors, terms = _line_systems(sums, _line_basis(sums.rows, line_time_s, lines_hz)[None], band_rows)
    matrix, vector = matrices[0], vectors[0]
    if float(sums.counts.sum()) - len(vector) < 8 * len(vector):
        return None
    try:
        factor = np.linalg.cholesky(matrix)  # the normal matrix is positive definite where the rows pin the model
    except np.linalg.LinAlgError:
        return None
    diagonal = np.diag(factor) ** 2
    if not np.all(np.isfinite(factor)) or diagonal.min() < 1e-12 * diagonal.max():
        return None
    solution = np.linalg.solve(matrix, vector)
    explained_squares = float(solution @ vector)
    if noise_variance is None:
        noise_variance = _noise_variance(sums, explained_squares, len(vector))
    return LineFit(solution[[0, terms]], explained_squares / noise_variance, noise_variance,
                   np.stack([solution[1:terms], solution[terms + 1:2 * terms]]))


#: Candidate frequencies whose normal equations are built and solved at once
#: (:func:`vibration_lines`): memory (a few MB) against Python's per-call cost.
CANDIDATE_BATCH = 64


def _explained_with(sums: RowSums, line_time_s: float, lines_hz: Sequence[float], candidates: np.ndarray,
                    noise_variance: float, band_rows: int = BAND_ROWS) -> np.ndarray:
    """What :func:`line_model_fit` with ``lines_hz`` and each candidate frequency added
    explains of one frame (in units of ``noise_variance``), for every candidate at once
    (a singular system: its least-squares projection)."""
    fixed = _line_basis(sums.rows, line_time_s, lines_hz)
    time = sums.rows.astype(np.float64) * line_time_s
    explained = np.full(len(candidates), np.nan)
    for first in range(0, len(candidates), CANDIDATE_BATCH):
        frequencies = candidates[first:first + CANDIDATE_BATCH]
        phase = 2 * np.pi * frequencies[:, None] * time[None, :]
        waves = np.stack([np.cos(phase), np.sin(phase)], axis=2)
        waves -= waves.mean(axis=1, keepdims=True)
        bases = np.concatenate([np.broadcast_to(fixed, (len(frequencies),) + fixed.shape), waves], axis=2)
        matrices, vectors, _ = _line_systems(sums, bases, band_rows)
        try:
            solutions = np.linalg.solve(matrices, vectors[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:  # a singular system in the batch: least squares, one by one
            solutions = np.stack([np.linalg.lstsq(matrix, vector, rcond=None)[0]
                                  for matrix, vector in zip(matrices, vectors)])
        explained[first:first + CANDIDATE_BATCH] = np.sum(solutions * vectors, axis=1) / noise_variance
    return explained



def chi_square_threshold(degrees_of_freedom: int, probability: float) -> float:
    """The value a chi-square of ``degrees_of_freedom`` (even) exceeds with ``probability``
    (its inverse survival function, scipy's ``chdtri``), without scipy, which is not a
    runtime dependency: for 2k degrees of freedom the survival function is
    exp(-x/2) sum_{i<k} (x/2)^i / i!, decreasing in x, so bisection finds it (in logs:
    the probabilities asked for are far in the tail)."""
    if degrees_of_freedom <= 0 or degrees_of_freedom % 2 or not 0 < probability < 1:
        raise ValueError(f"need an even, positive number of degrees of freedom and 0 < probability < 1, got "
                         f"{degrees_of_freedom}, {probability}")
    terms = np.arange(degrees_of_freedom // 2)
    log_factorials = np.concatenate(([0.0], np.cumsum(np.log(np.maximum(terms[1:], 1)))))

    def log_survival(x: float) -> float:
        half = x / 2
        logs = terms * math.log(half) - log_factorials
        top = logs.max()
        return -half + top + math.log(np.exp(logs - top).sum())

    target = math.log(probability)
    low, high = 1e-9, float(degrees_of_freedom)
    while log_survival(high) > target:
        high *= 2
    for _ in range(200):
        middle = 0.5 * (low + high)
        low, high = (middle, high) if log_survival(middle) > target else (low, middle)
        if high - low <= 1e-12 * high:
            break
    return 0.5 * (low + high)

def vibration_lines(reference: ScanReference, frames: Sequence[np.ndarray], shifts: Sequence[tuple[float, float]],
                    line_time_s: float, *, max_lines: int = MAX_VIBRATION_LINES,
                    false_alarm: float = LINE_FALSE_ALARM,
                    cancelled: Callable[[], bool] | None = None) -> tuple[float, ...] | None:
    """The stage's vibration lines (Hz), learned from ``frames`` scanned at rest (the
    stage still; their whole-frame shifts ``shifts`` against the reference, px) with
    ``line_time_s`` per row: a greedy search (as a line spectrum is cleaned), one line
    at a time, each the frequency whose sinusoid, fitted per frame with the lines found
    so far (:func:`line_model_fit`, free phase and amplitude per frame: a line need not
    keep its phase from frame to frame), explains the most of the frames' residues,
    refined between the frequencies tried; kept only while its gain stands above what
    noise would give with probability ``false_alarm`` over the whole search (chi-square
    with 4 degrees of freedom a frame, Bonferroni over the frequencies tried). Tried:
    from one cycle a scan to the rows' Nyquist frequency (every :data:`SAMPLE_STEP`-th
    row is sampled), :data:`LINE_OVERSAMPLING` per the scan's resolution. Empty when
    nothing stands out (no vibration, or none a frame's rows can resolve). ``cancelled``:
    asked between frames of the search; when it says True, the search stops and returns
    None (a teach superseded by the next one need not finish learning)."""
    sums = [row_sums(smoothed(frame), *predicted_frame(reference, dx, dy)) for frame, (dx, dy) in zip(frames, shifts)]
    if not sums or line_time_s <= 0:
        return ()
    scan_s = len(frames[0]) * line_time_s
    lowest, highest = 1.0 / scan_s, 1.0 / (2 * SAMPLE_STEP * line_time_s)
    candidates = np.arange(lowest, highest, 1.0 / (LINE_OVERSAMPLING * scan_s))
    threshold = chi_square_threshold(4 * len(sums), false_alarm / len(candidates))

    lines: tuple[float, ...] = ()
    while len(lines) < max_lines:
        # One noise scale per frame for every model compared: the residue of the model
        # with the most lines tried so far would favour it; the current model's is fair.
        fits = [line_model_fit(frame_sums, line_time_s, lines) for frame_sums in sums]
        if any(fit is None for fit in fits):
            return lines
        gains = -sum(fit.explained for fit in fits)
        for frame_sums, fit in zip(sums, fits):
            if cancelled is not None and cancelled():
                return None
            gains = gains + _explained_with(frame_sums, line_time_s, lines, candidates, fit.noise_variance)
        gains = np.where(np.isfinite(gains), gains, 0.0)
        best = int(np.argmax(gains))
        if gains[best] < threshold:
            break
        frequency = float(candidates[best])
        if 0 < best < len(candidates) - 1:  # the parabola's vertex through the best and its neighbours
            left, middle, right = gains[best - 1:best + 2]
            curvature = left - 2 * middle + right
            if curvature < 0:
                frequency += 0.5 * (left - right) / curvature * float(candidates[1] - candidates[0])
        lines += (round(frequency, 3),)
    return tuple(sorted(lines))
