""":class:`MotionEstimator`: the sections composed. Everything that depends only on the
reference (window, spectra, log-polar reference, turned references, FFT plans) is
computed once, one structure per resolution (:mod:`.resolutions`, and the rotation's
:class:`~.rotation.LogPolarReference` and :class:`~.rotation.ProbeReferences`);
:meth:`MotionEstimator.estimate` runs the per-frame part: rotation (:mod:`.rotation`),
then translation (:mod:`.translation`), with the SNR monitored (:mod:`.snr`). Sign
convention and confidence: :mod:`semservo.estimation`.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import replace
from typing import NamedTuple

import numpy as np

from semservo.estimation.common import MIN_SIZE, Motion, as_image
from semservo.estimation.masks import binary_region, mask_reference, polygon_mask
from semservo.estimation.raster import (ScanAveragedShift, ScanReference, band_start, dewaved, row_waves,
                                        scan_averaged_shift, vibration_lines)
from semservo.estimation.resolutions import FullResolution, HalfResolution, HalfTurnHeights, Search, kept_near
from semservo.estimation.rotation import (
    ANGLE_CANDIDATES, SMALL_TURN_PROBES, LogPolarReference, ProbeReferences, confidence_from_distinct,
    confidence_from_match, confidence_from_sharpness, overlap_windows, probe_top, rotate_about_centre,
    visible_window,
)
from semservo.estimation.snr import (
    DEFAULT_SNR_THRESHOLD_DB, FrameStatistics, estimate_snr_db, frame_statistics, gaussian_lowpass,
    noise_variance, snr_from_statistics,
)
from semservo.estimation.translation import BandFit, Shift, confidence_from_psr, refine_on_band

#: Turns smaller than this are not undone before measuring translation (they are still
#: reported): a rotation about the image centre adds no net shift, and undoing a turn
#: at the rotation estimate's noise floor (0.02-0.03 degree on real frames) costs a
#: resampling (0.4 ms) and adds interpolation. Larger turns are undone: on real frames,
#: skipping a 0.1 degree turn moves the shift by up to 0.06 px, a 0.05 degree turn by
#: about 0.02 px.
DEROTATE_ABOVE_DEG = 0.05
#: The search's peak for theta over that for theta + 180 (or the reverse) below which
#: the log-polar angle is in doubt (see ``MotionEstimator._estimate_with_rotation``): for
#: the right angle it was 3.4-40 on real scenes turned by up to 20 degrees and moved by
#: up to a quarter of the field (once 1.2, on a hole's disc), for a wrong one 1.0-1.9.
UNDECIDED_BELOW = 3.5
#: Of the candidates an undecided turn tries first (the log-polar peaks, each as it is and
#: turned by 180 degrees), one whose refined angle correlates with the reference at least
#: this well is taken without the scan over all turns (0.3 s a frame at 512 x 512, the
#: costly part), where the view moved by less than ``OVERLAP_ABOVE`` of the field (moved
#: a quarter of the field, a disc in a rim matched that well at a wrong turn).
#: The x5000 micropart (two long parallel edges, alike after a half turn) was undecided
#: on every frame at rest (ratio 1.5-2.9) with its right turn at 0.998-0.999.
MATCHED_ABOVE = 0.99
#: Then the correlation on the scene both images share is scanned over all turns, this
#: far apart (degrees; ``MotionEstimator._shared_scene_angles``), and each top narrowed
#: by halving the step twice. At the right turn that correlation fell by about 0.01
#: within 1.5 degrees, and stood 0.02-0.07 above every wrong turn's, on a hole moved by a
#: quarter of the field; on a finer texture (a synthetic rim's) its top is narrower.
SHARED_SCAN_STEP_DEG = 1.5
#: The least weight the windows over the shared scene may keep, as a fraction of the
#: fixed window's: a view moved (or turned) so far that they keep less shares too little.
MIN_OVERLAP = 0.1
#: A mask whose reference (the image it was drawn on) measures within this many pixels
#: of it is anchored to that image (``MotionEstimator``'s ``mask``): drawn or thresholded
#: on the object where it stands, its sub-pixel offset is the mask's, not a wish to move
#: the object by it. A mask farther off is a target somewhere else, taken as drawn.
MASK_ANCHORED_WITHIN_PX = 0.5
#: A partial frame against an anchored mask is measured against the mask's same rows,
#: anchored to the reference's same rows (a mask cut through its object reads the image
#: off by up to about half a pixel more than the whole mask does); rows whose image reads
#: further off than this (px) are not measured (the whole frame is used).
MASK_ROWS_ANCHORED_WITHIN_PX = 2.0
#: Partial frames' estimators kept (one per band of rows and turn setting, the most
#: recently used): a run's moves settle in a few bands; each is a few tens of MB at 1024 px.
ROW_ESTIMATORS_KEPT = 6
#: Views moved by more than this fraction of the frame's side (along rows or columns)
#: have their turn refined again under windows over the scene both images share
#: (``MotionEstimator._refine_on_overlap``).
OVERLAP_ABOVE = 0.08
#: A frame whose rows the fitted vibration lines move apart by more than this (px, at
#: most over its rows) has its turn measured again with the rows moved back
#: (``MotionEstimator._steadied``): below it, the shear cannot turn it by 0.01 degree.
DEWAVE_ABOVE_PX = 0.02


class Refined(NamedTuple):
    """The angle refined on the image (``MotionEstimator._refine_rotation``): the angle,
    its sharpness (0: no top, the image cannot tell the angle) and the shift at the
    best probe, in the axes of the frame turned back by the angle."""

    angle: float
    sharpness: float
    shift: Shift
    #: The normalized correlation at the top (0 when there is none).
    correlation: float = 0.0
    #: That correlation over the one two noisy views of one scene would reach.
    match: float = 0.0


class Turn(NamedTuple):
    """One candidate angle carried through: refined, with the angle the search turned the
    frame back by and the whole-pixel search that started the refinement (whose peak
    gives the confidence)."""

    angle: float
    sharpness: float
    shift: Shift
    searched_angle: float
    search: Search
    correlation: float = 0.0
    #: The search's peaks for theta and theta + 180 (which decided between them).
    heights: HalfTurnHeights | None = None
    match: float = 0.0
    #: How much more the best other angle misses of a perfect correlation (inf: none was
    #: tried), when several were.
    distinct: float = float("inf")


def _turned(x: float, y: float, theta: float) -> tuple[float, float]:
    """Where a turn by ``theta`` (radians, counter-clockwise as displayed) about the
    origin moves the point (x, y), minus the point: (dx, dy)."""
    return (x * np.cos(theta) + y * np.sin(theta) - x, -x * np.sin(theta) + y * np.cos(theta) - y)


def _distinct(search: Search) -> bool:
    """Whether the search's peak stands out of the noise (a confidence above zero), so
    the sub-pixel fit is kept near it (:func:`.kept_near`)."""
    return confidence_from_psr(search.psr) > 0.0


def _best_of(turns: list[Turn]) -> Turn:
    """Of refined candidate turns, the one whose angle correlates best with the
    reference; its ``distinct``: how much more the runner-up (another angle, more than a
    degree away) misses of a perfect correlation than it does."""
    best = max(turns, key=lambda turn: turn.correlation)
    others = [turn.correlation for turn in turns
              if turn.sharpness > 0.0 and abs((turn.angle - best.angle + 180) % 360 - 180) > 1.0]
    if others and best.correlation < 1.0:
        return best._replace(distinct=(1.0 - max(others)) / (1.0 - best.correlation))
    return best


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
        match wins, and ``confidence`` drops when several match equally. A mask drawn on
        the reference's own object (its image measured against the mask within
        :data:`MASK_ANCHORED_WITHIN_PX`) is anchored to it: that sub-pixel offset (a
        threshold's edges are not where the correlation puts a shaded, edge-brightened
        object) is taken off every estimate (``mask_offset``), so the target is where
        the reference was, as in the paper's case 6; a mask drawn elsewhere is the target
        as drawn (and measured on whole frames only, ``first_row`` below).
    mask_anchored_within_px : the line for that anchoring.
    window : apodization, see :func:`apodization_window`.
    snr_threshold_db : frames whose SNR is below this are filtered (section II-D).
    band : the highest spatial frequency (cycles/pixel) the sub-pixel fit uses.
    fft_effort : FFTW planner effort; plans are made once here and kept as wisdom.
    scan_averaged : refine the shift of every confident estimate to its mean over the
        scan's time (:mod:`.raster`): each band of 32 rows measured on its own and the
        bands averaged with random-effects weights (nearly uniform where vibration moves
        them apart), so vibration faster than a frame (each band a snapshot at its own
        time) is not weighted by where the texture lies. For frames scanned row by row
        under vibration (the estimator service's ``scan_averaged`` setting); not with a
        mask. About 8 ms more per 512 x 512 frame. Off by default: :mod:`.raster` says
        where it helps and where it does not yet.
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
        scan_averaged: bool = False,
        mask_anchored_within_px: float = MASK_ANCHORED_WITHIN_PX,
        steady_rows: bool = False,
    ):
        if precision not in ("full", "fast"):
            raise ValueError(f"precision must be 'full' or 'fast', not {precision!r}")
        reference = as_image(reference, "reference")
        if mask is None and reference.max() == reference.min():
            # Every shift and turn matches it alike: a run against it could only end
            # 'scene lost', seconds later (a blank upload, a beam blanked at the teach).
            raise ValueError(f"the reference is flat (every pixel {float(reference.min()):g}): there is nothing in it "
                             "to register against")
        # What a partial frame's estimator (:meth:`_rows_estimator`) is made from: the
        # reference as given, the mask as a boolean array, and the other settings.
        self._settings = dict(window=window, snr_threshold_db=snr_threshold_db, band=band, fft_effort=fft_effort,
                              angles=angles, mask_band=mask_band, precision=precision)
        self._given_reference = reference
        if isinstance(mask, np.ndarray) and mask.ndim == 2 and mask.dtype != bool:
            mask = binary_region(mask)  # a mask image: two levels, or refused
        self._mask_region = None if mask is None else (
            mask.astype(bool) if isinstance(mask, np.ndarray) and mask.ndim == 2 else polygon_mask(reference.shape, mask))
        self._rows_estimators: OrderedDict[tuple[int, bool], MotionEstimator] = OrderedDict()
        self._rows_lock = threading.Lock()
        if mask is not None:
            reference = mask_reference(reference, mask)
            rotation = False
        self.shape = reference.shape
        self.rotation = rotation
        #: Measure a frame again on its rows moved back by the vibration lines fitted in
        #: it (:meth:`_steadied`). Off by default: better at rest, worse in one closed loop.
        self.steady_rows = steady_rows
        self.scan_averaged = scan_averaged and mask is None
        self._scan_reference = ScanReference.of(reference) if self.scan_averaged else None
        #: The stage's vibration lines (Hz) the scan-averaged shift fits in every frame
        #: (:meth:`learn_vibration`); empty: the bands' random-effects mean.
        self.vibration_hz: tuple[float, ...] = ()
        self.precision = precision
        self.snr_threshold_db = snr_threshold_db
        self.reference_snr_db = estimate_snr_db(reference)
        lowpass = gaussian_lowpass(self.shape, mask_band) if mask is not None else None
        self._full = FullResolution.of(reference, window, band, lowpass, fft_effort)
        # The whole-pixel search runs on a pair halved by a binomial filter (four times
        # cheaper FFTs, and the filter lifts the SNR); full resolution is needed only
        # for the sub-pixel fit (precision="full"), which needs no inverse FFT.
        self._half = HalfResolution.of(self._full, window, band, mask_band if mask is not None else None)
        self._log_polar = LogPolarReference.of(self._full, angles, fft_effort) if rotation else None
        self._probes = ProbeReferences.of(self._full, self._half) if rotation else None
        # The reference's pixel noise, for how well a frame can match it at best.
        self._reference_half_noise = noise_variance(frame_statistics(self._full.reference)) / 4
        self._reference_signal_fraction = {
            filtered: self._half.band_signal_fraction(self._half.fit_reference_conjugate, self._half.moved_window(0, 0),
                                                      self._reference_half_noise, filtered)
            for filtered in (False, True)}
        #: The offset (dx, dy px) taken off every estimate: a mask's own against the
        #: reference it was drawn on (``mask`` above), else (0, 0).
        self.mask_offset = (0.0, 0.0)
        #: The mask is anchored to the reference's image (``mask``, above).
        self.mask_anchored = False
        if mask is not None:
            own = self._estimate(*self._check(self._given_reference), False)
            if own.confidence >= self.min_confidence and math.hypot(own.dx, own.dy) <= mask_anchored_within_px:
                self.mask_offset, self.mask_anchored = (float(own.dx), float(own.dy)), True

    def vibration_sample(self, frames) -> tuple[list[np.ndarray], list[tuple[float, float]]]:
        """The ``frames`` (at rest) this estimator measures confidently, and their
        whole-frame shifts: what :meth:`learn_vibration` learns from. It uses this
        estimator's buffers: call it from the thread that estimates."""
        kept, shifts = [], []
        for frame in frames:
            image, statistics = self._check(frame)
            motion = self._estimate(image, statistics, False)
            if motion.confidence >= self.min_confidence:
                kept.append(image)
                shifts.append((motion.dx, motion.dy))
        return kept, shifts

    def learn_vibration(self, frames, line_time_s: float, *, sample=None, cancelled=None) -> tuple[float, ...] | None:
        """Learn the stage's vibration lines from ``frames`` scanned at rest, each row
        ``line_time_s`` after the one before (:func:`.raster.vibration_lines`), and fit
        them in every scan-averaged shift from now on (:attr:`vibration_hz`). Frames this
        estimator cannot measure confidently are left out; fewer than two left, or an
        estimator without scan averaging: nothing is learned. ``sample``: what
        :meth:`vibration_sample` made of the frames, taken beforehand (then the
        learning, seconds long, may run in another thread while this estimator measures
        frames: it reads only the reference). ``cancelled``: asked during the search
        (:func:`.raster.vibration_lines`); True stops it, nothing learned, and returns
        None. Returns the lines (Hz)."""
        if not self.scan_averaged or not line_time_s or line_time_s <= 0:
            return ()
        kept, shifts = sample if sample is not None else self.vibration_sample(frames)
        if len(kept) < 2:
            return ()
        lines = vibration_lines(self._scan_reference, kept, shifts, float(line_time_s), cancelled=cancelled)
        if lines is None:
            return None
        self.vibration_hz = lines
        return self.vibration_hz

    def estimate(self, image, *, rotation: bool | None = None, scan_averaged: bool | None = None,
                 first_row: int = 0, line_time_s: float | None = None) -> Motion:
        """Motion of ``image`` against the reference. ValueError for bad input.

        ``rotation=False`` skips the rotation measurement of an estimator made with
        rotation (a third of the time, when nothing can turn); None: as made.
        ``scan_averaged=False`` skips the scan-averaged refinement of an estimator made
        with it (a frame scanned too fast for it to matter); None: as made.

        ``first_row`` > 0 measures a partial frame: only the rows from ``first_row`` on
        (rounded up to a whole band of :data:`~.raster.BAND_ROWS`, the returned Motion's
        ``first_row``), against the reference's same rows, as when the rows above were
        scanned while the stage still moved; the turn and shift are still about the
        frame's centre. The estimator for those rows is made once and kept (one per
        band). ValueError when fewer than :data:`~.common.MIN_SIZE` rows would be left.

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
        turned back by the refined angle (at full resolution with ``precision="full"``;
        on the scene both images share when the view moved far, :meth:`_fit_on_overlap`).
        An undecided angle is sought among more candidates, judged on the image: the
        log-polar peaks, and, unless one of them matches unmistakably (``MATCHED_ABOVE``),
        a scan over all turns (:meth:`_shared_scene_angles`, :func:`_best_of`).

        With ``scan_averaged``, last, the shift of an estimate confident enough to act on
        is averaged over the scan's bands of rows (:func:`.raster.scan_averaged_shift`);
        with the vibration lines learned (:meth:`learn_vibration`) and the scan's time
        per row ``line_time_s``, over the scan's time by fitting those lines.
        """
        if scan_averaged and not self.scan_averaged:
            raise ValueError("this estimator was made without scan averaging (scan_averaged=False)")
        if first_row:
            return self._estimate_rows(image, int(first_row), rotation, scan_averaged, line_time_s)
        image, statistics = self._check(image)
        motion = self._estimate(image, statistics, rotation)
        motion = self._from_mask_anchor(motion)
        if self.scan_averaged and scan_averaged is not False and motion.confidence >= self.min_confidence:
            refined = scan_averaged_shift(self._scan_reference, image, motion.dx, motion.dy, motion.rotation_deg,
                                          lines_hz=self.vibration_hz, line_time_s=line_time_s)
            if refined is not None:
                steadied = self._steadied(image, refined, rotation, line_time_s)
                return steadied if steadied is not None else replace(motion, dx=refined.dx, dy=refined.dy)
        return motion

    def _from_mask_anchor(self, motion: Motion) -> Motion:
        """``motion`` less the mask reference's own offset (none for other references)."""
        if self.mask_offset == (0.0, 0.0):
            return motion
        return replace(motion, dx=motion.dx - self.mask_offset[0], dy=motion.dy - self.mask_offset[1])

    def _steadied(self, image: np.ndarray, refined: ScanAveragedShift, rotation: bool | None,
                  line_time_s: float | None) -> Motion | None:
        """The motion of ``image`` measured again with its rows moved back by the vibration
        lines fitted in it (:func:`.raster.dewaved`), when the turn is measured and the
        lines move the rows apart by over :data:`DEWAVE_ABOVE_PX`; None otherwise, or when
        the steadied frame is not measured confidently.

        Why: the wavy rows are a shear, which the turn reads wherever the texture does not
        span the frame's rows (a cluster of particles in a corner): there the turn's error
        a frame was 0.039 degree RMS, 0.0070 on the steadied frame (and on a texture over
        the whole field 0.0064 and 0.0019), and the shift at the frame's centre, carried
        from the texture through the turn, 0.11-0.14 px RMS against 0.03-0.05. It costs a second
        estimate of such frames. Only with ``steady_rows`` (not the estimator service's):
        in the 5-DOF closed loop on the hole picture the view ended 0.062 px off on average
        (0.124 at worst) with it against 0.025 (0.073) without, a cause not yet found."""
        if not self.steady_rows or refined.line_fit is None or not (self.rotation and rotation is not False):
            return None
        waves = row_waves(refined.line_fit, image.shape[0], line_time_s, self.vibration_hz)
        if waves is None or float(np.ptp(waves, axis=0).max()) <= DEWAVE_ABOVE_PX:
            return None
        steady, statistics = self._check(dewaved(image, waves))
        motion = self._estimate(steady, statistics, rotation)
        motion = self._from_mask_anchor(motion)
        if motion.confidence < self.min_confidence:
            return None
        again = scan_averaged_shift(self._scan_reference, steady, motion.dx, motion.dy, motion.rotation_deg,
                                    lines_hz=self.vibration_hz, line_time_s=line_time_s)
        return motion if again is None else replace(motion, dx=again.dx, dy=again.dy)

    def _estimate_rows(self, image, first_row: int, rotation: bool | None, scan_averaged: bool | None,
                       line_time_s: float | None = None) -> Motion:
        """:meth:`estimate` on the rows from ``first_row`` (rounded up to a band)."""
        rows = band_start(first_row)
        if first_row < 0 or self.shape[0] - rows < MIN_SIZE:
            raise ValueError(f"first_row {first_row}: a partial frame needs at least {MIN_SIZE} of the "
                             f"{self.shape[0]} rows from a band's start")
        array = np.asarray(image)
        if array.shape != self.shape:
            raise ValueError(f"image is {array.shape[1] if array.ndim == 2 else array.shape} x "
                             f"{array.shape[0]}, the reference is {self.shape[1]} x {self.shape[0]}")
        if self._mask_region is not None and not self.mask_anchored:
            raise ValueError("a mask taken as drawn (not anchored to the image it was drawn on) is measured on "
                             "whole frames: cut at a row, its correlation with the image moves by up to half a "
                             "pixel")
        turns = self.rotation and rotation is not False
        rows_estimator = self._rows_estimator(rows, turns)
        rows_estimator.vibration_hz = self.vibration_hz  # the lines are the stage's, whatever the rows
        motion = rows_estimator.estimate(array[rows:], scan_averaged=scan_averaged, line_time_s=line_time_s)
        # The rows' estimator turns about their own centre, ``rows / 2`` below the
        # frame's: the same motion about the frame's centre moves by (R - I) times that.
        theta = np.radians(motion.rotation_deg)
        below = rows / 2.0
        dx = motion.dx - np.sin(theta) * below
        dy = motion.dy - (np.cos(theta) - 1.0) * below
        return replace(motion, dx=float(dx), dy=float(dy), first_row=rows)

    def prepare_rows(self, first_row: int, rotation: bool | None = None) -> None:
        """Make now what a partial frame from ``first_row`` will be measured with (the
        reference's rows from its band on: FFT plans, spectra, the turn's references), so
        that its estimate takes no longer than a whole frame's. Safe to call from another
        thread while this estimator measures frames (e.g. while the frame is scanned: FFT
        plans are made under one lock, :data:`~.plans.PLANNING_LOCK`); a no-op for rows
        that cannot be a partial frame, ValueError for rows an anchored mask cannot
        measure."""
        rows = band_start(first_row)
        if 0 < rows and self.shape[0] - rows >= MIN_SIZE and (self._mask_region is None or self.mask_anchored):
            self._rows_estimator(rows, self.rotation and rotation is not False)

    def _rows_estimator(self, rows: int, rotation: bool) -> "MotionEstimator":
        """The estimator of the reference's rows from ``rows`` on (with the turn's
        references or not), made once and kept among the last
        :data:`ROW_ESTIMATORS_KEPT`; one lock, so a frame waits for one being made. For an
        anchored mask, the mask's rows anchored to the reference's rows (ValueError when
        they read it more than :data:`MASK_ROWS_ANCHORED_WITHIN_PX` off)."""
        key = (rows, rotation)
        with self._rows_lock:
            made = self._rows_estimators.get(key)
            if made is None:
                mask = None if self._mask_region is None else self._mask_region[rows:]
                made = MotionEstimator(self._given_reference[rows:], rotation=rotation, mask=mask,
                                       scan_averaged=self.scan_averaged,
                                       mask_anchored_within_px=MASK_ROWS_ANCHORED_WITHIN_PX, **self._settings)
                if mask is not None and not made.mask_anchored:
                    raise ValueError(f"the mask's rows from {rows} on read the image they were drawn on more than "
                                     f"{MASK_ROWS_ANCHORED_WITHIN_PX:g} px off: measured on whole frames")
                self._rows_estimators[key] = made
                while len(self._rows_estimators) > ROW_ESTIMATORS_KEPT:
                    self._rows_estimators.popitem(last=False)
            self._rows_estimators.move_to_end(key)
            return made

    def _estimate(self, image: np.ndarray, statistics: FrameStatistics, rotation: bool | None) -> Motion:
        mean = float(statistics.mean)
        snr_db = snr_from_statistics(statistics)
        threshold = self.snr_threshold_db
        filtered = threshold is not None and (snr_db < threshold or self.reference_snr_db < threshold)
        if rotation and not self.rotation:
            raise ValueError("this estimator was made without rotation (rotation=False)")
        if self.rotation and rotation is not False:
            return self._estimate_with_rotation(image, mean, snr_db, filtered, noise_variance(statistics))
        if self.precision == "full":
            spectrum = self._full.spectrum(image, mean)
            search = self._half.search_full(spectrum)
            shift = self._full.fit(spectrum, search.shift, filtered, _distinct(search))
        else:
            search = self._half.search(self._half.spectrum_of(image, mean), self._half.reference_conjugate)
            shift = self._fit_fast(image, mean, search.shift, filtered, _distinct(search))
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
    def _fit_fast(self, image: np.ndarray, mean: float, shift: Shift, filtered: bool,
                  search_distinct: bool = True) -> Shift:
        """Steps 2 and 3 on the halved pair (``precision="fast"``): the full-resolution
        window moved by whole full-resolution pixels, then halved, so the scene
        weighting matches to within half a pixel."""
        if self._half.factor == 1:
            return self._full.fit(self._full.spectrum(image, mean), shift, filtered, search_distinct)
        spectrum = self._half.apodized_spectrum(image, mean, int(round(shift.dy)), int(round(shift.dx)))
        half = self._half

        def fitted(band) -> Shift:
            fit = half.fit(spectrum, half.fit_reference_conjugate, shift, band is half.filtered_fit_band)
            return Shift(fit.dy, fit.dx)

        band = half.filtered_fit_band if filtered else half.fit_band
        if self._full.near_search and search_distinct:
            return kept_near(shift, fitted, band, half.filtered_fit_band)
        return fitted(band)

    # -- rotation, then translation ---------------------------------------------------
    def _estimate_with_rotation(self, image: np.ndarray, mean: float, snr_db: float, filtered: bool,
                                noise: float) -> Motion:
        spectrum = self._full.spectrum(image, mean)
        small_image = self._half.factor == 1
        angle = self._log_polar.angle(spectrum, small_turns=small_image)
        if small_image:
            return self._estimate_small_with_rotation(image, mean, angle, snr_db, filtered)
        self._probes.load(image, noise)
        turn = self._refined_far(mean, self._turn_from(mean, spectrum, angle, filtered), filtered)
        if turn.heights.decisive < UNDECIDED_BELOW or turn.sharpness == 0.0:
            # Neither theta nor theta + 180 matches clearly, or the image shows no top
            # near the log-polar angle: the log-polar peak may be the wrong angle (the
            # magnitude spectrum's strongest peak can be the scene's axis-aligned edges
            # or the window's, a turn near 90 degrees read as 0; on a sparse scene whose
            # view moved far, its second or third peak was the turn, or none was), or
            # the search may not tell theta from theta + 180. So the next log-polar
            # peaks are tried too, each as it is and turned by 180 degrees, and the best
            # turns of a scan over all turns of the correlation on the shared scene;
            # each judged by how well the image correlates at its refined angle. The
            # scan (the costly part) only when the search's peak stands out of the
            # noise (a frame without one is refused whatever its turn: a flat grey
            # would pay for it on every frame of a lost scene), and unless the view
            # moved little and a log-polar candidate matches unmistakably
            # (MATCHED_ABOVE; moved far, a disc in a rim matched at a wrong turn too).
            turns = self._turns(mean, spectrum, [(candidate, flip) for candidate in
                                                 [angle] + self._log_polar.candidates(ANGLE_CANDIDATES)[1:]
                                                 for flip in (False, True)], filtered)
            matched = not self._moved_far(turn) and max(candidate.correlation for candidate in turns) >= MATCHED_ABOVE
            if _distinct(turn.search) and not matched:
                turns += self._turns(mean, spectrum, [(candidate, False) for candidate in
                                                      self._shared_scene_angles(mean, filtered)], filtered)
            turn = _best_of(turns)
        return self._fit_turned(image, mean, spectrum, turn, snr_db, filtered)

    def _refined_far(self, mean: float, turn: Turn, filtered: bool) -> Turn:
        """``turn`` refined again on the scene both images show when the view moved far
        (:meth:`_refine_on_overlap`, also where the first refinement found no top: its
        windows, moved with the content, cut at the frame's edge), else as it is."""
        return self._on_overlap(mean, turn, filtered) if self._moved_far(turn) else turn

    def _moved_far(self, turn: Turn) -> bool:
        """Whether the view moved by more than ``OVERLAP_ABOVE`` of the field."""
        return max(abs(turn.search.dy), abs(turn.search.dx)) > OVERLAP_ABOVE * min(self.shape)

    def _on_overlap(self, mean: float, turn: Turn, filtered: bool) -> Turn:
        """``turn`` refined again on the scene both images show (:meth:`_refine_on_overlap`),
        its correlation there kept; as it was, with correlation 0, when that finds no top."""
        refined = self._refine_on_overlap(mean, turn, filtered)
        if refined.sharpness > 0.0:
            return turn._replace(angle=refined.angle, sharpness=refined.sharpness, shift=refined.shift,
                                 correlation=refined.correlation, match=refined.match)
        return turn._replace(sharpness=0.0, correlation=0.0, match=0.0)

    def _shared_scene_angles(self, mean: float, filtered: bool, count: int = ANGLE_CANDIDATES) -> list[float]:
        """The ``count`` turns (degrees, within [-180, 180)) at which the halved frame,
        turned back and searched (the whole-pixel shift), correlates best with the
        reference on the scene both show (:meth:`_shared_scene_correlation`): a scan
        every ``SHARED_SCAN_STEP_DEG`` over the full turn, local tops only, highest first,
        each narrowed by halving the step twice.

        For a view moved far the other measures mislead: the log-polar spectrum carries
        the content the two views do not share, and the search's peak under the fixed
        window (scanned over turns before) favours matching what fills both windows'
        middles. On a scene that is
        mostly one round object (a hole's disc) that is the object turned about its own
        centre, which matches at every turn: the search's peak at the right turn was
        below its median over turns. The correlation on the shared scene, at each turn's
        own best shift, is what the candidates are finally judged by; at the object's
        wrong turns the rest of the shared scene does not match (0.92-0.96 against
        0.98-0.998 at the right turn, a hole moved by a quarter of the field)."""
        step = SHARED_SCAN_STEP_DEG
        window = self._half.moved_window(0, 0)
        half_turns = np.arange(-180.0, 0.0, step)
        scores = np.empty((2, half_turns.size))
        for index, angle in enumerate(half_turns):
            # A turn and the turn plus a half turn share the frame turned back (flipped)
            # and the window it carries (the window is symmetric).
            visible = visible_window(window, float(angle))
            for flip in (0, 1):
                scores[flip, index] = self._shared_scene_correlation(mean, float(angle) + 180.0 * flip, filtered,
                                                                     visible)
        angles, scores = np.concatenate([half_turns, half_turns + 180.0]), scores.ravel()
        tops = (scores >= np.roll(scores, 1)) & (scores > np.roll(scores, -1))
        order = np.flatnonzero(tops)[np.argsort(scores[tops])[::-1]][:count]
        found = []
        for index in order:
            best, best_score = float(angles[index]), float(scores[index])
            for half_step in (step / 2, step / 4):
                for angle in (best - half_step, best + half_step):
                    score = self._shared_scene_correlation(mean, angle, filtered)
                    if score > best_score:
                        best, best_score = angle, score
            found.append((best + 180.0) % 360.0 - 180.0)
        return found

    def _shared_scene_correlation(self, mean: float, angle: float, filtered: bool,
                                  visible: np.ndarray | None = None) -> float:
        """The normalized band-limited correlation (the refinement's, eq. 18-22) of the
        halved frame turned back by ``angle`` with the reference, at the search's shift,
        both weighted by windows over the scene they then share (:func:`overlap_windows`;
        ``visible``: the window the turned-back frame carries, when made already); -1
        when they share too little."""
        half, probes = self._half, self._probes
        search, _ = self._half_search(mean, angle)
        window = half.moved_window(0, 0)
        windows = overlap_windows(window, angle, (search.dy / 2, search.dx / 2), visible)
        if windows.reference.sum() < MIN_OVERLAP * window.sum():
            return -1.0
        frame_spectrum = np.array(half.weighted_spectrum(probes.turned_back(angle), windows.frame))
        reference = np.conj(half.weighted_spectrum(probes.halved[0], windows.reference))
        return half.fit(frame_spectrum, reference, search.shift, filtered, with_correlation=True).correlation

    def _turns(self, mean: float, spectrum: np.ndarray, candidates: list[tuple[float, bool]], filtered: bool
               ) -> list[Turn]:
        """The candidate angles (each with whether to turn it by 180 degrees), refined
        (on the scene both show, when the view moved far)."""
        return [self._refined_far(mean, self._turn_from(mean, spectrum, candidate, filtered, flip=flip), filtered)
                for candidate, flip in candidates]

    def _turn_from(self, mean: float, spectrum: np.ndarray, angle: float, filtered: bool,
                   flip: bool | None = None) -> Turn:
        """From a log-polar angle: the search (theta or theta + 180: as the search's peaks
        say, or as ``flip`` says) and the refinement."""
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
        heights = self._half.half_turn_heights(searched, reference, as_is=search.height)
        if heights.turned_is_better if flip is None else flip:
            angle += 180.0 if angle < 0 else -180.0
            search, _ = self._half_search(mean, angle)
        refined = self._refine_rotation(mean, angle, search.shift, filtered)
        return Turn(refined.angle, refined.sharpness, refined.shift, angle, search, refined.correlation, heights,
                    refined.match)

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
        turned_back, middle, frame = self._probe_frame(angle)
        spectrum = half.windowed_spectrum(frame, mean, shift)
        # The unturned reference's fit starts the others (a turn moves the best shift
        # little: by the turn times the distance from the window's centre).
        best = half.fit(spectrum, probes.conjugates[0], shift, filtered, with_correlation=True)
        fits = {0: best}

        def fit(probe: int) -> BandFit:
            if probe not in fits:
                fits[probe] = half.fit(spectrum, probes.conjugates[probe], best[:2], filtered, with_correlation=True)
            return fits[probe]

        reachable = np.sqrt(self._reference_signal_fraction[filtered] * half.band_signal_fraction(
            spectrum, half.moved_window(int(round(shift[0])), int(round(shift[1]))), probes.half_noise, filtered))
        return self._probe_parabola(fit, turned_back, middle, angle, shift, reachable)

    def _refine_on_overlap(self, mean: float, turn: Turn, filtered: bool) -> Refined:
        """:meth:`_refine_rotation` again, for a frame whose view has moved far: both the
        frame and the reference copies weighted by windows over the scene they share
        (:func:`overlap_windows`), made for this frame.

        The fixed window's fit weights the frame by the window moved with the content,
        which runs off the frame's edge while it still weighs (a hard cut), against a
        reference that keeps the content the frame lacks: both bias the correlation over
        the probe turns, by up to 0.3 degree at shifts of a quarter of the field. The
        frame is the one the first refinement used (turned back by the searched angle,
        or not at all for small turns), and the probes are centred on its answer. The
        copies are turned about the reference's centre, not the overlap's, so each
        probe's fit starts where that turn moves the overlap's centre.
        """
        probes, half = self._probes, self._half
        turned_back, _, frame = self._probe_frame(turn.searched_angle)
        residual = turn.angle - turned_back
        middle = int(np.clip(round(residual / probes.step_deg), -SMALL_TURN_PROBES, SMALL_TURN_PROBES))
        search = turn.search.shift
        window = half.moved_window(0, 0)
        windows = overlap_windows(window, turned_back, (search.dy / 2, search.dx / 2))
        if windows.reference.sum() < MIN_OVERLAP * window.sum():
            return Refined(turn.angle, 0.0, turn.shift)  # too little shared to tell a turn
        spectrum = np.array(half.weighted_spectrum(frame, windows.frame))
        frame_fraction = half.band_signal_fraction(spectrum, windows.frame, probes.half_noise, filtered)
        reference_fraction = []
        # From the reference's centre to the overlap's, in full-resolution pixels.
        lever_x, lever_y = 2 * windows.centroid[0], 2 * windows.centroid[1]
        fits: dict[int, BandFit] = {}

        def fit(probe: int) -> BandFit:
            if probe not in fits:
                reference = np.conj(half.weighted_spectrum(probes.halved[probe], windows.reference))
                if not reference_fraction:
                    reference_fraction.append(half.band_signal_fraction(reference, windows.reference,
                                                                        self._reference_half_noise, filtered))
                # Where the overlap's centre goes under the turn left to this probe,
                # against where it goes under the turn the search saw (the unturned copy).
                moves = [_turned(lever_x, lever_y, np.radians(turn_deg)) for turn_deg in
                         (residual - probe * probes.step_deg, residual)]
                start = (search.dy + moves[0][1] - moves[1][1], search.dx + moves[0][0] - moves[1][0])
                fits[probe] = half.fit(spectrum, reference, start, filtered, with_correlation=True)
            return fits[probe]

        fit(middle)  # the first fit, which measures the reference's share of signal
        return self._probe_parabola(fit, turned_back, middle, turn.angle, turn.shift,
                                    np.sqrt(frame_fraction * reference_fraction[0]))

    def _probe_frame(self, angle: float) -> tuple[float, int, np.ndarray]:
        """The halved frame the probes are fitted to for a turn ``angle``: (the turn it was
        turned back by, the probe nearest the angle left, the frame). Small turns are
        not turned back (see ``SMALL_TURN_PROBES``)."""
        probes = self._probes
        if abs(angle) <= SMALL_TURN_PROBES * probes.step_deg:
            return 0.0, int(round(angle / probes.step_deg)), probes.half_image
        return angle, 0, probes.turned_back(angle)

    def _probe_parabola(self, fit, turned_back: float, middle: int, angle: float, shift: Shift,
                        reachable: float) -> Refined:
        """Climb to the probe whose fit (``fit(probe)``: a :class:`BandFit`) correlates
        best, at most two probes from ``middle`` and within the probes made, and fit a
        parabola through it and its neighbours; ``angle`` and ``shift`` are answered
        unchanged, with sharpness 0, when there is no top. ``reachable``: the correlation
        two noisy views of one scene would reach (the match is the top's over it)."""

        def correlation(probe: int) -> float:
            return fit(probe).correlation

        probe_deg = self._probes.step_deg
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
        refined = turned_back + (middle + top.offset) * probe_deg
        best_shift = Shift(fit(middle).dy, fit(middle).dx)
        if turned_back == 0.0 and abs(refined) > DEROTATE_ABOVE_DEG:
            # The fits were in the frame's own axes; the fit that follows turns it back.
            theta = np.deg2rad(refined)
            y, x = best_shift
            best_shift = Shift(x * np.sin(theta) + y * np.cos(theta), x * np.cos(theta) - y * np.sin(theta))
        return Refined(float(refined), float(top.sharpness), best_shift, float(top.height),
                       float(top.height / reachable) if reachable > 0 else 0.0)

    def _fit_turned(self, image: np.ndarray, mean: float, spectrum: np.ndarray, turn: Turn, snr_db: float,
                    filtered: bool) -> Motion:
        """The final fit of the frame turned back by the refined angle (``spectrum``: the
        frame's own, used as it is below ``DEROTATE_ABOVE_DEG``)."""
        rotation_confidence = min(confidence_from_sharpness(turn.sharpness), confidence_from_match(turn.match),
                                  confidence_from_distinct(turn.distinct))
        if self.precision == "fast":
            # On the halved frame turned back, under the full-resolution window moved by
            # the whole-pixel shift and halved (as the fast fit's reference).
            half_spectrum = self._half.windowed_spectrum(self._probes.turned_back(turn.angle), mean, turn.shift)
            fit = self._half.fit(half_spectrum, self._half.fit_reference_conjugate, turn.shift, filtered)
            return _motion(Shift(fit.dy, fit.dx), turn.angle, True, turn.search, snr_db, filtered,
                           rotation_confidence)
        derotated = abs(turn.angle) > DEROTATE_ABOVE_DEG
        frame = rotate_about_centre(image, -turn.angle, self._full.frame_buffer()) if derotated else image
        shift = self._fit_on_overlap(frame, turn, derotated, filtered) if self._moved_far(turn) else None
        if shift is None:
            if derotated:
                spectrum = self._full.spectrum(frame, mean)
            shift = self._full.fit(spectrum, turn.shift, filtered, _distinct(turn.search))
        return _motion(shift, turn.angle, derotated, turn.search, snr_db, filtered, rotation_confidence)

    def _fit_on_overlap(self, frame: np.ndarray, turn: Turn, derotated: bool, filtered: bool) -> Shift | None:
        """The final sub-pixel fit (eq. 18-22) of a view moved far, on the scene both
        images share: the frame (turned back by the turn when ``derotated``) and the
        reference weighted by windows over it (:func:`overlap_windows`, at full
        resolution), from the refinement's shift and kept near it (:func:`kept_near`);
        None when they share too little.

        The fixed window's fit weights the reference under the window moved with the
        content, which keeps what the frame does not show, at full weight, and runs off
        the frame's edge; on a scene whose strong edges lie there (a hole's rim moved by
        a quarter of the field) that pulled the shift by 0.3-0.9 px, 0.01-0.08 on the
        shared scene."""
        full = self._full
        windows = overlap_windows(full.window, turn.angle if derotated else 0.0, turn.shift)
        if windows.reference.sum() < MIN_OVERLAP * full.window.sum():
            return None
        frame_spectrum = np.array(full.weighted_spectrum(frame, windows.frame))
        reference = np.conj(full.weighted_spectrum(full.reference, windows.reference))

        def fitted(band) -> Shift:
            fit = refine_on_band(frame_spectrum, reference, band, turn.shift, workspace=full.band_workspace)
            return Shift(fit.dy, fit.dx)

        band = full.filtered_fit_band if filtered else full.fit_band
        if not _distinct(turn.search):
            return fitted(band)
        return kept_near(turn.shift, fitted, band, full.filtered_fit_band)

    def _estimate_small_with_rotation(self, image: np.ndarray, mean: float, angle: float, snr_db: float,
                                      filtered: bool) -> Motion:
        """Images under 128 pixels a side have no halved pair: the log-polar angle is
        used as it is (not refined), the search and the fit run at full resolution."""
        derotated = abs(angle) > DEROTATE_ABOVE_DEG
        turned = rotate_about_centre(image, -angle, self._full.frame_buffer()) if derotated else image
        spectrum = self._full.spectrum(turned, mean)
        search = self._half.search_full(spectrum)
        if self._half.half_turn_heights(self._half.cropped, self._half.cropped_reference_conjugate,
                                        as_is=search.height).turned_is_better:
            angle += 180.0 if angle < 0 else -180.0
            derotated = True
            spectrum = self._full.spectrum(rotate_about_centre(image, -angle, self._full.frame_buffer()), mean)
            search = self._half.search_full(spectrum)
        return _motion(self._full.fit(spectrum, search.shift, filtered, _distinct(search)), angle, derotated, search, snr_db, filtered)
