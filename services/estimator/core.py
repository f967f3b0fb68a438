"""The estimator's core: the taught reference and frame -> motion, without sockets."""

from __future__ import annotations

import base64
import logging
import threading
import time
import uuid
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from semservo.errors import CommandError
from semservo.estimation import MotionEstimator
from semservo.estimation.common import MIN_SIZE
from semservo.estimation.masks import binary_region
from semservo.estimation.raster import (BAND_ROWS, PARTIAL_FRAME_FROM, SCAN_AVERAGED_FROM_S, rows_scanned_after,
                                       scan_lasted_s)
from semservo.estimation.tilt import (MAX_FINE_TEACH_SWEEPS, MAX_TAUGHT_UNCERTAINTY_DEG, MAX_TEACH_SWEEPS, KernelDepths,
                                      TiltEstimate, as_taught, check_sweep, content_shifts, egi_tilt_between,
                                      kernel_depths, line_against, measured_against, plan_fine_sweep, plan_sweep,
                                      pool_depths, pooled_tilt, rows_seen_square_on, sampled_as_finely,
                                      undo_foreshortening, undoes_foreshortening, wants_another_sweep,
                                      wants_fine_sweeps)
from semservo.instruments import scan_middle_ns
from semservo.imagefiles import ImageFileError, read_image
from semservo.messages import ACQUISITION_FIELDS, MotionEstimate
from semservo.wire import Frame

log = logging.getLogger("estimator")


#: The live frames' content positions kept for steadying focus sweeps
#: (:meth:`EstimatorCore.sweep_content_shifts`): minutes of frames at any usual rate.
CONTENT_TRACK_FRAMES = 4096
#: Only frames measured at least this confidently enter the track (the controller's
#: default line for acting on an estimate).
CONTENT_TRACK_MIN_CONFIDENCE = 0.5
#: A partial frame's rows begin at least this long after the move settled (ns): the
#: stage's clock and the scan generator's are two computers' under NTP (a millisecond or
#: so apart on a LAN), and a row is 0.6-0.9 ms at the paper's dwell times.
PARTIAL_FRAME_MARGIN_NS = 2_000_000


class TeachError(CommandError):
    """A teach request that cannot be honoured; the previous reference is kept."""

    code_name = "bad_request"

    def __init__(self, message: str):
        super().__init__(self.code_name, message)

    def __str__(self) -> str:
        return self.message


class NotEnoughFrames(TeachError):
    """Fewer frames have arrived than the teach asks to average: ask again shortly."""

    code_name = "not_enough_frames"
    transient = True


class NoTiltReference(TeachError):
    """The tilts cannot be measured: no taught focus sweep for this reference (yet)."""

    code_name = "no_tilt_reference"


@dataclass
class Reference:
    id: str
    kind: str  # "frame", "image" or "mask"
    shape: tuple[int, int]
    pixel_size_nm: float | None
    taught_at_ns: int
    detail: dict[str, Any] = field(default_factory=dict)
    acquisition: dict[str, Any] = field(default_factory=dict)  # what its source says of the acquisition

    def describe(self) -> dict:
        return {"id": self.id, "kind": self.kind, "shape": list(self.shape), "pixel_size_nm": self.pixel_size_nm,
                "taught_at_ns": self.taught_at_ns, "acquisition": dict(self.acquisition), **self.detail}


def acquisition_of(frame: Frame | None) -> dict[str, Any]:
    """The acquisition fields a frame's source knows (absent: not known)."""
    if frame is None:
        return {}
    return {key: getattr(frame.header, key) for key in ACQUISITION_FIELDS if getattr(frame.header, key) is not None}


def _finite_pair(first: float, second: float) -> tuple[float, float] | None:
    """Two numbers for the wire, or None when either is not finite (JSON has no NaN)."""
    return (float(first), float(second)) if np.isfinite(first) and np.isfinite(second) else None


def decode_upload(encoded: str, *, with_metadata: bool = False, data_bar="auto"):
    """Pixels of a base64-encoded PNG or TIFF upload (and, ``with_metadata``, what the
    file says of its acquisition); a data bar cropped as ``data_bar`` says
    (:func:`semservo.imagefiles.read_sem_image`)."""
    try:
        raw = base64.b64decode(encoded, validate=True)
    except (ValueError, TypeError) as error:
        raise TeachError(f"image_b64 is not base64: {error}") from None
    try:
        pixels, metadata = read_image(raw, data_bar=data_bar)
    except ImageFileError as error:
        raise TeachError(str(error)) from None
    return (pixels, metadata) if with_metadata else pixels


#: The smallest polygon a mask reference may be drawn from (square pixels): below this
#: the outline the mask is matched on is a few pixels of noise.
MIN_MASK_AREA_PX = 256

#: The most frames a reference may average (kept as the last received).
MAX_FRAMES_AVERAGED = 16
#: The most frames at rest a teach learns the stage's vibration lines from
#: (:meth:`EstimatorCore._learn_vibration`): the frames a teach usually averages, and
#: learning from four 512 x 512 frames takes under a second.
VIBRATION_FRAMES = 4


@dataclass(frozen=True)
class TiltSettings:
    """How tilts are measured from focus sweeps (section II-B-2)."""

    depth_of_field_um: float = 3.5  # the SEM's at the sweep's settings: sets the sweep's step
    centre_um: float = 0.0  # where the first sweep is centred (the working distance offset in focus)
    max_tilt_deg: float = 15.0  # the first sweep is wide enough for this much tilt
    kernel_px: int = 32
    method: str = "plane"  # or "egi": the paper's extended Gaussian image correlation
    #: The focus measure the kernels' curves are read by (:data:`semservo.estimation.tilt.FOCUS_MEASURES`):
    #: the taught sweep and every sweep measured against it alike.
    focus_measure: str = "normalized_variance"
    #: The most focus sweeps a teach takes of the taught pose, pooled, before it refuses
    #: (:func:`semservo.estimation.tilt.wants_another_sweep`).
    teach_sweeps: int = MAX_TEACH_SWEEPS
    #: Where those cannot pin the tilts, the most fine sweeps the teach takes instead, about
    #: the depths they found (:func:`semservo.estimation.tilt.wants_fine_sweeps`, ``plan_fine_sweep``; 0: none).
    fine_teach_sweeps: int = MAX_FINE_TEACH_SWEEPS
    #: During a run, sweeps near the goal (tilts within this many degrees of the taught
    #: ones) pinned more loosely than the teach's aim are pooled too (:meth:`EstimatorCore.sweep_again`).
    pool_near_deg: float = 0.5


@dataclass
class TiltReference:
    """The taught pose's focus sweep: its kernel depths and plane."""

    reference_id: str
    depths: np.ndarray
    estimate: TiltEstimate
    pixel_size_um: float
    frames: int
    working_distances: tuple[float, ...] = ()
    #: Taught from fine sweeps (the wide ones could not pin the tilts): a run's sweep that
    #: cannot pin them is followed by a fine one too (:meth:`EstimatorCore.fine_sweep_after`).
    fine: bool = False

    @property
    def grid(self) -> tuple[float, float]:
        """The taught sweep's (first working distance, step): later sweeps sample the same places."""
        return self.working_distances[0], (self.working_distances[-1] - self.working_distances[0]) / (self.frames - 1)


@dataclass
class TeachPool:
    """The taught pose's focus sweeps so far, while a teach pools them: each one's kernel
    depths and sweep step, and the tilts of them all pooled."""

    reference_id: str
    depth_maps: list[KernelDepths] = field(default_factory=list)
    steps: list[float] = field(default_factory=list)
    #: How far each sweep's content moved while it scanned (px; None: not steadied).
    content_moved_px: list[float | None] = field(default_factory=list)
    estimate: TiltEstimate | None = None
    #: The fine sweeps' working distances once the wide ones could not pin the tilts
    #: (None: the wide sweeps so far); the pool then holds the fine sweeps only.
    fine_sweep: tuple[float, ...] | None = None
    #: The wide sweeps' outcome, kept for the teach's record once it sweeps finely.
    wide: dict | None = None


def _prepare_rows(estimator: MotionEstimator, bands: list[int], rotation: bool) -> None:
    """Make the partial frames' estimators of ``bands`` (a thread of its own)."""
    for band in bands:
        try:
            estimator.prepare_rows(band, rotation)
        except ValueError as error:  # rows an anchored mask cannot measure: those frames are used whole
            log.debug("no partial frames from row %d: %s", band, error)
        except Exception:  # noqa: BLE001 - a frame that needs it makes it itself, and says why if it cannot
            log.exception("preparing the partial frames' estimators failed")
            return


class EstimatorCore:
    def __init__(self, *, rotation: bool = True, precision: str = "full", fft_effort: str = "FFTW_MEASURE",
                 counters: Counter | None = None, tilt: TiltSettings | None = None, scan_averaged: bool = True,
                 vibration_lines: bool = True):
        self.rotation = rotation
        #: Shifts averaged over the scan's bands of rows (:mod:`semservo.estimation.raster`).
        self.scan_averaged = scan_averaged
        #: The stage's vibration lines learned at a teach and fitted in those averages.
        self.vibration_lines = vibration_lines
        # Whether each frame's rotation is measured (a run that cannot turn the sample
        # switches it off: translation alone takes a third of the time).
        self.measure_rotation = rotation
        self.precision = precision
        self.fft_effort = fft_effort
        self.estimator: MotionEstimator | None = None
        self.reference: Reference | None = None
        self.latest: Frame | None = None
        self.recent: deque[Frame] = deque(maxlen=MAX_FRAMES_AVERAGED)
        self.last_estimate: MotionEstimate | None = None
        self.counters: Counter = counters if counters is not None else Counter()
        self.tilt_settings = tilt or TiltSettings()
        self.tilt_reference: TiltReference | None = None
        self.measure_tilts = False
        self.undone_tilt: dict | None  # the tilts frames are undone with (set with last_tilt)
        self.last_tilt = None  # the latest tilt measurement against the reference
        self.tilt_sequence = 0
        self.tilt_error: str | None = None
        #: The taught pose's focus sweep after a teach with tilts: it runs in the background
        #: (``services.estimator.tilts``); its state, scans done and outcome.
        self.tilt_teach: dict | None = None
        #: The taught pose's sweeps so far, while a teach pools them (:meth:`teach_tilt`).
        self.teach_pool: TeachPool | None = None
        #: What the reference looks like (the taught image; for a mask, the live frame it
        #: was drawn on): the gateway and the dashboard show it.
        self.reference_pixels: np.ndarray | None = None
        #: Where the live frames' content was against the reference, and when (the middle
        #: of each scan, ns; dx, dy px): a sweep's frames are moved back by it
        #: (:meth:`sweep_content_shifts`). Appended by the frame thread, read by the tracker's.
        self.content_track: deque[tuple[int, float, float]] = deque(maxlen=CONTENT_TRACK_FRAMES)
        self._track_lock = threading.Lock()
        #: How far the last sweep's content moved while it scanned (px), None when it could
        #: not be steadied (:meth:`sweep_depths`).
        self.last_sweep_moved_px: float | None = None
        #: When the last move a run told of (:meth:`moved`) has settled (Unix ns): the frame
        #: whose scan spans it is measured on its rows scanned after it (a partial frame).
        self.moved_settles_at_ns: int | None = None

    # -- tilts (focus sweeps) ----------------------------------------------------
    @property
    def last_tilt(self) -> dict | None:
        """The latest tilt measurement against the reference (None: none yet)."""
        return self._last_tilt

    @last_tilt.setter
    def last_tilt(self, measured: dict | None) -> None:
        # Frames are undone with the last tilts measured with confidence: a sweep that
        # could not tell them leaves the foreshortening as it was (undoing nothing at a
        # few degrees of tilt would turn the view by tenths of a degree).
        if measured is None or measured.get("confidence", 0) > 0:
            self.undone_tilt = measured
        self._last_tilt = measured

    def next_sweep(self) -> list[float]:
        """The working distances (um) of the next sweep: wide for the first, tracking
        after (:func:`semservo.estimation.tilt.plan_sweep`)."""
        settings, reference = self.tilt_settings, self.tilt_reference
        if self.latest is None or self.latest.header.pixel_size_nm is None:
            raise TeachError("a focus sweep needs frames with a pixel size; none has arrived")
        pool = self.teach_pool
        if (pool is not None and pool.fine_sweep is not None and self.reference is not None
                and pool.reference_id == self.reference.id):
            return list(pool.fine_sweep)
        field_um = self.latest.pixels.shape[1] * self.latest.header.pixel_size_nm / 1000
        last = self.last_tilt if self.last_tilt and self.last_tilt.get("confidence", 0) > 0 else None
        if last is not None:
            tilt = (last["absolute_alpha_deg"], last["absolute_beta_deg"])
            return plan_sweep(last["centre_um"], settings.depth_of_field_um, field_um, tilt_deg=tilt,
                              grid=reference.grid if reference is not None else None).tolist()
        if reference is not None:
            tilt = (reference.estimate.alpha_deg, reference.estimate.beta_deg)
            # Not yet measured since teaching: anything up to the stage's usual tilt from there.
            return plan_sweep(reference.estimate.centre_depth, settings.depth_of_field_um, field_um,
                              max_tilt_deg=settings.max_tilt_deg + max(map(abs, tilt)), grid=reference.grid).tolist()
        return plan_sweep(settings.centre_um, settings.depth_of_field_um, field_um,
                          max_tilt_deg=settings.max_tilt_deg).tolist()

    def sweep_depths(self, sweep: np.ndarray, working_distances: list[float], pixel_size_nm: float | None,
                     frame_times_ns: list[int] | None = None) -> KernelDepths:
        """A sweep's kernel depths and their uncertainties
        (:func:`semservo.estimation.tilt.kernel_depths`; NaN where no clear peak); TeachError for input that is not a sweep. With ``frame_times_ns``
        (the middle of each frame's scan, as the image server tells it), the frames are
        first moved back by how far their content moved meanwhile, read off the live
        frames (:meth:`sweep_content_shifts`); ``last_sweep_moved_px`` says how far, or
        None when the live frames did not cover the sweep (it is then read as scanned)."""
        if pixel_size_nm is None:
            raise TeachError("the sweep's frames carry no pixel size: tilts cannot be measured")
        kernel = self.tilt_settings.kernel_px
        try:
            check_sweep(sweep, working_distances, pixel_size_nm / 1000, kernel)
        except ValueError as error:
            raise TeachError(f"focus sweep: {error}") from None
        shifts = self.sweep_content_shifts(frame_times_ns) if frame_times_ns is not None else None
        if shifts is not None and np.abs(shifts).max() >= min(np.shape(sweep)[1:]) / 4:
            shifts = None  # not the same view: read as scanned, its kernels' content changed anyway
        self.counters["sweeps_steadied" if shifts is not None else "sweeps_not_steadied"] += 1
        self.last_sweep_moved_px = float(np.hypot(*np.ptp(shifts, axis=0))) if shifts is not None else None
        return kernel_depths(sweep, working_distances, kernel, pixel_size_nm / 1000, shifts,
                             measure=self.tilt_settings.focus_measure)

    def sweep_content_shifts(self, frame_times_ns: list[int]) -> np.ndarray | None:
        """How far each frame of a sweep had its content moved from the sweep's middle
        frame (frames x 2, px), from the live frames' shifts against this reference
        around the same times (:func:`semservo.estimation.tilt.content_shifts`); None
        when they do not cover the sweep (no reference, no confident frames then)."""
        with self._track_lock:
            track = np.array(self.content_track, dtype=np.float64).reshape(-1, 3)
        if len(track) < 2:
            return None
        return content_shifts(np.asarray(frame_times_ns, dtype=np.float64), track[:, 0], track[:, 1], track[:, 2])

    def sweep_again(self, depth_maps: list[KernelDepths], working_distances: list[float],
                    pixel_size_nm: float | None) -> bool:
        """During a run, whether the tracker should sweep the same view again and pool it
        with these sweeps' depths before it reports the tilts: when they cannot pin them
        (refused for their uncertainty, and more sweeps could,
        :func:`semservo.estimation.tilt.wants_another_sweep`), or when the tilts are
        within ``TiltSettings.pool_near_deg`` of the taught ones but pinned more loosely
        than the teach's aim (near the goal, where the run converges on the measurement,
        a sweep's noise of +-0.1 degree would be acted on as tilt); at most
        ``TiltSettings.teach_sweeps`` in all (fine sweeps against a finely taught reference:
        as many as its teach could take, ``fine_teach_sweeps``). Far from the goal one sweep
        is enough: the next move is larger than its noise."""
        reference = self.tilt_reference
        most = self.tilt_settings.teach_sweeps
        if reference is not None and reference.fine and sampled_as_finely(working_distances, reference.grid[1]):
            most = max(most, self.tilt_settings.fine_teach_sweeps)
        if reference is None or len(depth_maps) >= most:
            return False
        estimate = measured_against(self.pooled_estimate(depth_maps, working_distances, pixel_size_nm),
                                    reference.estimate)
        if not wants_another_sweep(estimate, most, line_against(reference.estimate)):
            return False
        if estimate.confidence <= 0:
            return True
        near = max(abs(estimate.alpha_deg - reference.estimate.alpha_deg),
                   abs(estimate.beta_deg - reference.estimate.beta_deg))
        return near <= self.tilt_settings.pool_near_deg

    def fine_sweep_after(self, depth_maps: list[KernelDepths], working_distances: list[float],
                         pixel_size_nm: float | None) -> list[float] | None:
        """During a run against a finely taught reference: where these sweeps of one view
        (coarser than the taught grid) cannot pin the tilts for their uncertainty alone, the
        fine sweep about the depths they found that the tracker sweeps next instead, on the
        taught grid (:func:`semservo.estimation.tilt.plan_fine_sweep`); None otherwise,
        and always against a reference the wide sweeps taught (its runs are as before)."""
        reference = self.tilt_reference
        if reference is None or not reference.fine or len(working_distances) < 2:
            return None
        if sampled_as_finely(working_distances, reference.grid[1]):
            return None  # already as fine as the teach
        estimate = self.pooled_estimate(depth_maps, working_distances, pixel_size_nm)
        if not wants_fine_sweeps(estimate, line_against(reference.estimate)):
            return None
        fine = plan_fine_sweep(pool_depths(depth_maps).depths, working_distances, self.tilt_settings.depth_of_field_um,
                               grid=reference.grid)
        return None if fine is None else fine.tolist()

    def pooled_estimate(self, depth_maps: list[KernelDepths], working_distances: list[float],
                        pixel_size_nm: float | None) -> TiltEstimate:
        """The tilts of the pooled depths of sweeps of one view on these working distances."""
        if pixel_size_nm is None:
            raise TeachError("the sweep's frames carry no pixel size: tilts cannot be measured")
        step = (working_distances[-1] - working_distances[0]) / (len(working_distances) - 1)
        return pooled_tilt(depth_maps, self.tilt_settings.kernel_px, pixel_size_nm / 1000, float(step))

    def teach_tilt(self, sweep: np.ndarray, working_distances: list[float], pixel_size_nm: float | None,
                   reference_id: str | None = None, frame_times_ns: list[int] | None = None) -> dict | None:
        """One focus sweep of the taught pose (with the reference image just taught,
        ``reference_id`` when given), pooled with the ones before it for this reference
        (:func:`semservo.estimation.tilt.pooled_tilt`). Returns the reference's
        description when the tilts are taught; None when the sweeps so far pin them too
        loosely and another sweep of the same view may pin them better (at most
        ``TiltSettings.teach_sweeps`` in all: :func:`semservo.estimation.tilt.wants_another_sweep`;
        ``teach_pool`` holds them and their estimate so far). Where the wide sweeps cannot
        pin the tilts for their uncertainty alone, the teach sweeps the view finely about the
        depths they found instead (``teach_pool.fine_sweep``, which :meth:`next_sweep`
        plans; at most ``TiltSettings.fine_teach_sweeps``, pooled alike; the taught grid is
        then theirs); refused with the reason (how
        well the tilts were pinned, after how many sweeps) when it cannot tell the tilts
        (a flat scene, focus outside it, a depth of field too large for the field's depth)."""
        if self.reference is None:
            raise TeachError("teach an image before its tilt sweep")
        if reference_id is not None and reference_id != self.reference.id:
            raise TeachError(f"reference {reference_id} was replaced by {self.reference.id} during its focus sweep")
        depths = self.sweep_depths(sweep, working_distances, pixel_size_nm, frame_times_ns)
        pool = self.teach_pool
        if pool is None or pool.reference_id != self.reference.id:
            pool = TeachPool(self.reference.id)
        pool.depth_maps.append(depths)
        pool.content_moved_px.append(self.last_sweep_moved_px)
        pool.steps.append((working_distances[-1] - working_distances[0]) / (len(working_distances) - 1))
        pool.estimate = pooled_tilt(pool.depth_maps, self.tilt_settings.kernel_px, pixel_size_nm / 1000,
                                    float(np.mean(pool.steps)))
        estimate = pool.estimate
        settings = self.tilt_settings
        fine = pool.fine_sweep is not None
        most = settings.fine_teach_sweeps if fine else settings.teach_sweeps
        if wants_another_sweep(estimate, most, MAX_TAUGHT_UNCERTAINTY_DEG, begun=fine):
            self.teach_pool = pool
            return None
        if pool.fine_sweep is None and settings.fine_teach_sweeps > 0 and wants_fine_sweeps(estimate):
            fine = plan_fine_sweep(pool_depths(pool.depth_maps).depths, working_distances, settings.depth_of_field_um)
            if fine is not None:
                # The wide sweeps found the depths; the fine ones, on the flanks of the
                # kernels' focus curves, pin them (the pool starts again with them).
                self.teach_pool = TeachPool(pool.reference_id, fine_sweep=tuple(float(value) for value in fine),
                                            wide={"sweeps": estimate.sweeps, "frames": len(sweep),
                                                  "alpha_uncertainty_deg": estimate.alpha_uncertainty_deg,
                                                  "beta_uncertainty_deg": estimate.beta_uncertainty_deg})
                return None
        self.teach_pool = None
        estimate = as_taught(estimate)  # refused where it would leave its runs less than it took
        if estimate.confidence <= 0:
            swept = "focus sweep" if estimate.sweeps == 1 else f"{estimate.sweeps} focus sweeps"
            if pool.fine_sweep is not None:
                wide = pool.wide["sweeps"]
                swept = f"{wide} wide focus sweep{'s' if wide > 1 else ''} and {estimate.sweeps} fine"
            raise NoTiltReference(f"the reference's {swept} cannot tell the tilts: {estimate.reason}")
        self.tilt_reference = TiltReference(self.reference.id, pool_depths(pool.depth_maps).depths, estimate,
                                            pixel_size_nm / 1000, len(sweep),
                                            tuple(float(value) for value in working_distances),
                                            fine=pool.fine_sweep is not None)
        self.last_tilt = None
        self.reference.detail["tilt"] = {
            "alpha_deg": estimate.alpha_deg, "beta_deg": estimate.beta_deg, "centre_um": estimate.centre_depth,
            "kernels_used": estimate.kernels_used, "frames": len(sweep), "sweeps": estimate.sweeps,
            "alpha_uncertainty_deg": estimate.alpha_uncertainty_deg,
            "beta_uncertainty_deg": estimate.beta_uncertainty_deg,
            "content_moved_px": [None if moved is None else round(moved, 3) for moved in pool.content_moved_px],
            "fine": pool.fine_sweep is not None, "wide_sweeps": pool.wide}
        return self.reference.describe()

    def tilt_from_sweep(self, sweep: np.ndarray, working_distances: list[float], pixel_size_nm: float | None, *,
                        scan_started_at_ns: int | None = None, source_interval_s=None, took_s: float | None = None,
                        earlier: list[KernelDepths] | None = None, sweep_depth_map: KernelDepths | None = None,
                        frame_times_ns: list[int] | None = None) -> dict:
        """The tilts of a sweep against the taught one's: alpha and beta (degrees, the
        convention of :mod:`semservo.estimation.tilt`) with a confidence (0: not measured, the
        reason given). With ``method="egi"`` the rotation between the two EGIs.
        ``earlier``: the kernel depths of earlier sweeps of the same view on the same
        working distances (:meth:`sweep_depths`), pooled with this one's
        (:func:`semservo.estimation.tilt.pooled_tilt`); ``sweep_depth_map``: this sweep's, when
        made already (the tracker made it to decide whether to sweep again), else made
        here, steadied with ``frame_times_ns`` (:meth:`sweep_depths`)."""
        reference = self.tilt_reference
        if reference is None or self.reference is None or reference.reference_id != self.reference.id:
            raise NoTiltReference("no tilt reference: teach with tilts=true first (a focus sweep at the taught pose)")
        started = time.perf_counter()
        this = sweep_depth_map if sweep_depth_map is not None else self.sweep_depths(sweep, working_distances,
                                                                                     pixel_size_nm, frame_times_ns)
        maps = [*(earlier or []), this]
        # Refused where, against the taught reading, the tilts would be pinned too loosely.
        estimate = measured_against(self.pooled_estimate(maps, working_distances, pixel_size_nm), reference.estimate)
        depths = pool_depths(maps).depths
        if self.tilt_settings.method == "egi":
            alpha, beta, peak = egi_tilt_between(reference.depths, depths, self.tilt_settings.kernel_px,
                                                 reference.pixel_size_um)
            confidence = min(estimate.confidence, 1.0 if np.isfinite(alpha) else 0.0)
        else:
            alpha = estimate.alpha_deg - reference.estimate.alpha_deg
            beta = estimate.beta_deg - reference.estimate.beta_deg
            confidence = estimate.confidence
        self.tilt_sequence += 1
        result = {
            "tilt_seq": self.tilt_sequence, "reference_id": reference.reference_id,
            "alpha_deg": float(alpha) if confidence > 0 else None, "beta_deg": float(beta) if confidence > 0 else None,
            "confidence": float(confidence), "reason": estimate.reason,
            "absolute_alpha_deg": estimate.alpha_deg, "absolute_beta_deg": estimate.beta_deg,
            "centre_um": estimate.centre_depth, "kernels_used": estimate.kernels_used,
            "kernels_total": estimate.kernels_total, "frames": len(sweep), "sweeps": estimate.sweeps,
            "alpha_uncertainty_deg": estimate.alpha_uncertainty_deg,
            "beta_uncertainty_deg": estimate.beta_uncertainty_deg,
            "working_distances_um": [float(value) for value in working_distances],
            "scan_started_at_ns": scan_started_at_ns, "source_interval_s": source_interval_s, "sweep_s": took_s,
            "content_moved_px": self.last_sweep_moved_px,
            "estimation_ms": (time.perf_counter() - started) * 1e3,
            # A small depth map for the dashboard: kernel depths from the centre (um), null where unclear.
            "depth_map_um": [[None if not np.isfinite(v) else round(float(v - estimate.centre_depth), 3)
                              for v in row] for row in depths],
        }
        self.last_tilt = result
        self.counters["tilt_measurements"] += 1
        return result

    # -- teaching -------------------------------------------------------------
    def _install(self, pixels: np.ndarray, kind: str, pixel_size_nm: float | None, mask=None, *,
                 acquisition: dict | None = None, shown: np.ndarray | None = None, **detail) -> dict:
        try:
            estimator = MotionEstimator(pixels, rotation=self.rotation, mask=mask, precision=self.precision,
                                        fft_effort=self.fft_effort, scan_averaged=self.scan_averaged)
        except ValueError as error:
            raise TeachError(str(error)) from None
        # Only now, with the new estimator built, is the old reference replaced.
        self.estimator = estimator
        # A new reference needs its own sweep, and its own track of the content.
        self.tilt_reference, self.last_tilt, self.tilt_teach, self.teach_pool = None, None, None, None
        with self._track_lock:
            self.content_track.clear()
        self.reference_pixels = np.array(pixels if shown is None else shown)
        self.reference = Reference(
            id=uuid.uuid4().hex[:12], kind=kind, shape=pixels.shape, pixel_size_nm=pixel_size_nm,
            taught_at_ns=time.time_ns(), detail=detail, acquisition=acquisition or {},
        )
        self.counters["references_taught"] += 1
        return self.reference.describe()

    def teach_latest(self, frames: int = 1, scanned_after_ns: int | None = None) -> dict:
        """The latest frame becomes the reference, or the mean of the latest ``frames``
        (frame integration, as an SEM does for a clean image: it also averages out the
        stage vibration each single scan samples, which at x5000 is ~0.2 px; the stage
        must stand still over those frames). ``scanned_after_ns``: only frames whose scan
        began then or later (the stage's last move had settled): a frame scanned during a
        move is a blend of two views, and a reference averaged with it is a place the
        stage never was (a run then 'converged' 10 px from the target)."""
        if self.latest is None:
            raise NotEnoughFrames("no frame has been received yet; is the image server running?")
        if not isinstance(frames, int) or not 1 <= frames <= self.recent.maxlen:
            raise TeachError(f"frames must be a whole number from 1 to {self.recent.maxlen}, got {frames!r}")
        candidates = list(self.recent)
        if scanned_after_ns:
            candidates = [frame for frame in candidates
                          if (frame.header.scan_started_at_ns or frame.header.acquired_at_ns) >= scanned_after_ns]
        chosen = candidates[-frames:]
        if len(chosen) < frames:
            since = " scanned since the stage's last move settled" if scanned_after_ns else " received so far"
            raise NotEnoughFrames(f"only {len(chosen)} frames{since}; {frames} asked for averaging")
        shapes = {frame.pixels.shape for frame in chosen}
        if len(shapes) > 1 or len({frame.header.pixel_size_nm for frame in chosen}) > 1:
            raise TeachError("the scan changed during the frames to average; teach again")
        frame = chosen[-1]
        pixels = np.array(frame.pixels) if frames == 1 else np.mean([f.pixels for f in chosen], axis=0, dtype=np.float32)
        intervals = [f.header.source_interval_s for f in chosen]
        # On the source's clock (the fake lab's simulated time), when the reference was
        # scanned: what the simulator's truth for the taught pose is averaged over.
        scanned = [intervals[0][0], intervals[-1][1]] if all(intervals) else None
        described = self._install(pixels, "frame", frame.header.pixel_size_nm, acquisition=acquisition_of(frame),
                                  frame_seq=frame.header.seq, source=frame.header.source, frames_averaged=frames,
                                  source_interval_s=scanned)
        # The frames known to be at rest (scanned after the stage settled; without that
        # time, only those averaged) teach the stage's vibration lines.
        at_rest = [f for f in (candidates if scanned_after_ns else chosen)
                   if f.pixels.shape == frame.pixels.shape and f.header.pixel_size_nm == frame.header.pixel_size_nm]
        self._learn_vibration(at_rest[-VIBRATION_FRAMES:])
        return self.describe_reference()

    def _learn_vibration(self, frames: list[Frame]) -> None:
        """Learn the stage's vibration lines from ``frames`` at rest, in the background
        (seconds: :meth:`MotionEstimator.learn_vibration`), for the estimator just made;
        until then, and when they cannot be learned, frames are scan-averaged by their
        bands. What happened is the reference's ``vibration``."""
        estimator, reference = self.estimator, self.reference
        line_times = [self._line_time_s(frame) for frame in frames]
        if not estimator.scan_averaged or not self.vibration_lines:
            reference.detail["vibration"] = {"state": "none", "lines_hz": [], "frames": len(frames),
                                              "reason": "scan averaging is off" if not estimator.scan_averaged
                                              else "vibration lines are off (settings)"}
            return
        if len(frames) < 2 or not all(line_times):
            reference.detail["vibration"] = {
                "state": "none", "lines_hz": [], "frames": len(frames),
                "reason": "fewer than 2 frames at rest" if len(frames) < 2 else "the frames do not say how long "
                                                                                  "their scan lasted"}
            return
        if not all(self._scanned_slowly(frame) for frame in frames):
            reference.detail["vibration"] = {"state": "none", "lines_hz": [], "frames": len(frames),
                                              "reason": f"scans shorter than {SCAN_AVERAGED_FROM_S * 1e3:g} ms are "
                                                        "not scan-averaged"}
            return
        reference.detail["vibration"] = {"state": "learning", "lines_hz": [], "frames": len(frames)}
        line_time = float(np.median(line_times))
        # The frames' whole-frame shifts now, in the thread that estimates (the
        # estimator's buffers are not shared); the search, seconds long, in the
        # background, on the reference alone.
        sample = estimator.vibration_sample([f.pixels for f in frames])

        def learn() -> None:
            try:
                # A teach since makes another estimator: this one's lines are not needed.
                lines = estimator.learn_vibration(None, line_time, sample=sample,
                                                  cancelled=lambda: self.estimator is not estimator)
                if lines is None:
                    return
            except Exception as error:  # the reference stands; its frames are averaged by bands
                log.warning("vibration lines not learned: %s", error)
                reference.detail["vibration"] = {"state": "none", "lines_hz": [], "frames": len(frames),
                                                 "reason": f"learning failed: {error}"}
                return
            reference.detail["vibration"] = {"state": "learned" if lines else "none",
                                             "lines_hz": [round(value, 2) for value in lines], "frames": len(frames),
                                             **({} if lines else {"reason": "no line stands above the noise"})}
            log.info("vibration lines of reference %s: %s Hz (from %d frames at rest)", reference.id,
                     ", ".join(f"{value:.2f}" for value in lines) or "none", len(frames))

        threading.Thread(target=learn, daemon=True, name="vibration-lines").start()

    def teach_image(self, pixels: np.ndarray, label: str = "upload", acquisition: dict | None = None,
                    source_interval_s: list[float] | None = None) -> dict:
        """An image as the reference (an upload, a file, a stored target, a one-off slow
        scan): it must be of the current scan's size. Its pixel size is the live
        frames' (the scale the run measures in) unless the image says its own."""
        if self.latest is not None and pixels.shape != self.latest.pixels.shape:
            rows, cols = self.latest.pixels.shape
            raise TeachError(f"image is {pixels.shape[1]} x {pixels.shape[0]}, the current scan is {cols} x {rows}")
        known = dict(acquisition or {})
        pixel_size = known.get("pixel_size_nm") or (self.latest.header.pixel_size_nm if self.latest is not None
                                                    else None)
        detail = {"label": label}
        if source_interval_s is not None:
            detail["source_interval_s"] = list(source_interval_s)
        return self._install(pixels, "image", pixel_size, acquisition=known or acquisition_of(self.latest), **detail)

    def teach_mask(self, *, polygon=None, mask: np.ndarray | None = None) -> dict:
        """A mask reference (paper case 6) drawn on the latest frame's shape and levels."""
        if self.latest is None:
            raise TeachError("a mask is drawn on the live image: no frame has been received yet")
        if (polygon is None) == (mask is None):
            raise TeachError("give either polygon corner points or a mask image")
        if mask is not None and mask.shape != self.latest.pixels.shape:
            raise TeachError(f"mask is {mask.shape[1]} x {mask.shape[0]}, the current scan is "
                             f"{self.latest.pixels.shape[1]} x {self.latest.pixels.shape[0]}")
        if mask is not None:
            try:
                shape_mask = binary_region(mask)
            except ValueError as error:
                raise TeachError(str(error)) from None
        else:
            try:
                shape_mask = [tuple(map(float, point)) for point in polygon]
            except (TypeError, ValueError):
                raise TeachError("polygon must be a list of [x, y] corner points") from None
        if polygon is not None:
            if len(shape_mask) < 3:
                raise TeachError(f"a polygon needs at least 3 corner points, got {len(shape_mask)}")
            rows, cols = self.latest.pixels.shape
            # Corners are clicked on the live image; a little outside it is fine (a mask
            # cut by the edge), far outside is a mistake (and overflows the rasterizer).
            if not all(len(point) == 2 and -cols <= point[0] <= 2 * cols and -rows <= point[1] <= 2 * rows
                       for point in shape_mask):
                raise TeachError(f"polygon corner points must be [x, y] pairs of finite numbers on or near the "
                                 f"{cols} x {rows} image")
            x, y = np.array(shape_mask).T
            area = 0.5 * abs(float(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1))))  # shoelace
            if area < MIN_MASK_AREA_PX:
                raise TeachError(f"the polygon encloses {area:.0f} square pixels; a mask needs at least "
                                 f"{MIN_MASK_AREA_PX}")
        detail = {"polygon": [list(point) for point in shape_mask]} if polygon is not None else {}
        return self._install(np.array(self.latest.pixels), "mask", self.latest.header.pixel_size_nm,
                             mask=shape_mask, acquisition=acquisition_of(self.latest), **detail)

    def warm_up(self) -> None:
        """Compile the per-frame kernels now (numba compiles on first use, seconds when
        its on-disk cache is cold), so the first teach and estimate answer promptly."""
        rows, cols = np.mgrid[0:64, 0:64]
        texture = (np.sin(cols / 3.0) * np.cos(rows / 5.0) + np.sin((rows + cols) / 7.0)).astype(np.float32)
        estimator = MotionEstimator(texture, rotation=self.rotation, precision=self.precision,
                                    fft_effort="FFTW_ESTIMATE")
        estimator.estimate(np.roll(texture, 2, axis=1))

    def measure(self, rotation: bool | None, tilts: bool | None = None) -> dict:
        """Measure rotation per frame or not (None: as configured); measure the tilts
        from focus sweeps, one after another, or not (None: not)."""
        if rotation and not self.rotation:
            raise TeachError("rotation is off in this estimator's configuration (SEMSERVO_ESTIMATOR__ROTATION)")
        if tilts and (self.tilt_reference is None or self.reference is None
                      or self.tilt_reference.reference_id != self.reference.id):
            teach = self.tilt_teach
            if teach is not None and self.reference is not None and teach["reference_id"] == self.reference.id:
                if teach["state"] == "sweeping":
                    raise NoTiltReference(f"no tilt reference yet: the taught pose's focus sweep is still scanning "
                                          f"({teach['scanned']} of {teach['frames']} frames); start when it is done")
                raise NoTiltReference(f"no tilt reference: the taught pose's focus sweep failed: {teach['error']}")
            raise NoTiltReference("no tilt reference: teach with tilts=true first (a focus sweep at the taught pose)")
        self.measure_rotation = self.rotation if rotation is None else bool(rotation)
        self.measure_tilts = bool(tilts)
        if self.measure_tilts:
            self.last_tilt = None  # the first sweep of a run is the wide one
        return {"rotation": self.measure_rotation, "tilts": self.measure_tilts}

    def moved(self, settles_at_ns: int) -> dict:
        """A run moved the stage, settling at ``settles_at_ns``: the frame whose scan spans
        that time is measured on its rows scanned after it, when they are enough
        (:func:`semservo.estimation.raster.rows_scanned_after`) and its source times its
        scans; the run acts on that partial frame a scan sooner than on the next whole one."""
        self.moved_settles_at_ns = int(settles_at_ns)
        estimator = self.estimator
        if estimator is None:
            return {"partial_from_ns": None}
        # What that frame will be measured with is made while it scans (in a thread: the
        # first partial frame of a run at a new band costs 0.1-0.6 s to prepare, more than
        # the loop's latency): the band the next scan's timing predicts, and its neighbours.
        predicted = self._predicted_first_row(self.moved_settles_at_ns)
        if predicted:
            rotation = self.measure_rotation and estimator.rotation
            bands = [row for row in (predicted - BAND_ROWS, predicted, predicted + BAND_ROWS) if row > 0]
            threading.Thread(target=_prepare_rows, args=(estimator, bands, rotation), daemon=True,
                             name="estimator-rows").start()
        return {"partial_from_ns": self.moved_settles_at_ns}

    def _predicted_first_row(self, settles_at_ns: int) -> int | None:
        """The first row of the next scan scanned after ``settles_at_ns``, from the last
        frames' timing (the next scan starts after the same gap and lasts as long)."""
        if not self.recent or self.recent[-1].header.scan_started_at_ns is None:
            return None
        last = self.recent[-1].header
        lasted = last.acquired_at_ns - last.scan_started_at_ns
        gap = 0
        if len(self.recent) > 1:
            gap = max(last.scan_started_at_ns - self.recent[-2].header.acquired_at_ns, 0)
        start = last.acquired_at_ns + gap
        if start > settles_at_ns:  # the scan after the last one began after the move: the one in progress
            start = last.scan_started_at_ns
        return rows_scanned_after(last.shape[0], start, start + lasted, settles_at_ns)

    def clear(self) -> dict:
        had = self.reference is not None
        self.estimator = None
        self.reference = None
        self.reference_pixels = None
        self.tilt_reference, self.last_tilt, self.measure_tilts, self.tilt_teach = None, None, False, None
        self.teach_pool = None
        with self._track_lock:
            self.content_track.clear()
        return {"cleared": had}

    # -- per frame ------------------------------------------------------------
    def process(self, frame: Frame) -> MotionEstimate | None:
        """The motion of ``frame`` against the reference; None when there is no reference
        or the frame cannot be compared (counted, with the reason in ``last_error``)."""
        self.latest = frame
        self.recent.append(frame)
        if self.estimator is None:
            self.counters["frames_without_reference"] += 1
            return None
        if frame.pixels.shape != self.estimator.shape:
            self.counters["frames_wrong_shape"] += 1
            raise ValueError(f"frame {frame.header.seq} is {frame.header.shape}, the reference is "
                             f"{self.estimator.shape}; teach again after changing the scan")
        started = time.perf_counter()
        pixels = frame.pixels
        # One snapshot: the tracker's thread may measure the next sweep meanwhile.
        latest, tilt = (self.last_tilt, self.undone_tilt) if self.measure_tilts else (None, None)
        undone = tilt if tilt and undoes_foreshortening(tilt.get("alpha_deg"), tilt.get("beta_deg")) else None
        if undone:
            # Seen square on, as the reference was: a tilted view is foreshortened, which
            # the log-polar angle reads as degrees of turn (14 at 15 degrees of tilt).
            pixels = undo_foreshortening(pixels, undone["alpha_deg"], undone["beta_deg"])
        first_row = self._first_row_after_move(frame, undone)
        averaged = self.estimator.scan_averaged and self._scanned_slowly(frame)
        rotation = self.measure_rotation and self.estimator.rotation
        line_time = self._line_time_s(frame)
        try:
            motion = self.estimator.estimate(pixels, rotation=rotation, scan_averaged=averaged, first_row=first_row,
                                             line_time_s=line_time)
        except ValueError as error:  # rows the estimator cannot measure (a mask all one level there)
            if not first_row:
                raise
            self.counters["partial_frames_refused"] += 1
            log.info("frame %d: its rows after the move cannot be measured (%s); measured whole", frame.header.seq, error)
            motion = self.estimator.estimate(pixels, rotation=rotation, scan_averaged=averaged, line_time_s=line_time)
        elapsed_ms = (time.perf_counter() - started) * 1e3
        now = time.time_ns()
        header = frame.header
        rows = {}
        if motion.first_row:
            fraction = motion.first_row / header.shape[0]
            rows_from_ns = header.scan_started_at_ns + round(fraction * (header.acquired_at_ns - header.scan_started_at_ns))
            source = header.source_interval_s
            rows = {"first_row": motion.first_row, "rows_scanned_from_ns": rows_from_ns,
                    "rows_source_interval_s": None if source is None else
                    (source[0] + fraction * (source[1] - source[0]), source[1])}
            self.counters["partial_frames"] += 1
        estimate = MotionEstimate(
            seq=frame.header.seq, reference_id=self.reference.id,
            dx_px=motion.dx, dy_px=motion.dy, rotation_deg=motion.rotation_deg,
            confidence=min(1.0, max(0.0, motion.confidence)), snr_db=motion.snr_db, filtered=motion.filtered,
            pixel_size_nm=frame.header.pixel_size_nm,
            frame_acquired_at_ns=frame.header.acquired_at_ns, frame_published_at_ns=frame.header.published_at_ns,
            frame_scan_started_at_ns=frame.header.scan_started_at_ns,
            frame_source_interval_s=frame.header.source_interval_s,
            published_at_ns=now, estimation_ms=elapsed_ms, scan_averaged=averaged,
            latency_ms=(now - frame.header.published_at_ns) / 1e6,
            **rows, **self._tilt_fields(latest),
        )
        self.counters["estimates"] += 1
        self.last_estimate = estimate
        if estimate.confidence >= CONTENT_TRACK_MIN_CONFIDENCE and np.isfinite([motion.dx, motion.dy]).all():
            seen_from = rows.get("rows_scanned_from_ns", frame.header.scan_started_at_ns)
            with self._track_lock:
                self.content_track.append((scan_middle_ns(seen_from, frame.header.acquired_at_ns),
                                           float(motion.dx), float(motion.dy)))
        return estimate

    def _first_row_after_move(self, frame: Frame, undone: dict | None = None) -> int:
        """The first row of ``frame`` to measure: after the move a run told of, when its
        scan spans the move's settling and enough rows are left (a partial frame); else 0
        (the whole frame, stale or not). Only for a source that times its scans (its
        ``source_interval_s``: a scan generator's own start and end, not a file's times).
        ``undone``: the tilts whose foreshortening the frame is resampled to undo, which
        reaches rows up (:func:`semservo.estimation.tilt.rows_seen_square_on`)."""
        header, after = frame.header, self.moved_settles_at_ns
        if after is None or header.scan_started_at_ns is None or header.source_interval_s is None:
            return 0
        rows = header.shape[0]
        first_row = rows_scanned_after(rows, header.scan_started_at_ns, header.acquired_at_ns,
                                       after + PARTIAL_FRAME_MARGIN_NS)
        if first_row and undone:
            first_row = rows_seen_square_on(first_row, header.shape, undone["alpha_deg"], undone["beta_deg"])
        return first_row if first_row and rows - first_row >= max(PARTIAL_FRAME_FROM * rows, MIN_SIZE) else 0

    def _scanned_slowly(self, frame: Frame) -> bool:
        """Whether ``frame``'s scan lasted long enough for the scan-averaged shift
        (:data:`semservo.estimation.raster.SCAN_AVERAGED_FROM_S`; unknown: yes)."""
        lasted = self._scan_lasted_s(frame)
        return lasted is None or lasted >= SCAN_AVERAGED_FROM_S

    def _scan_lasted_s(self, frame: Frame) -> float | None:
        """How long ``frame``'s scan lasted, on its source's clock where it has one
        (:func:`semservo.estimation.raster.scan_lasted_s`)."""
        header = frame.header
        earlier = [f for f in self.recent if f.header.seq < header.seq]
        previous = earlier[-1].header.acquired_at_ns if earlier else None
        return scan_lasted_s(header.shape, source_interval_s=header.source_interval_s, dwell_ns=header.dwell_ns,
                             scan_started_at_ns=header.scan_started_at_ns, acquired_at_ns=header.acquired_at_ns,
                             previous_acquired_at_ns=previous)

    @staticmethod
    def _line_time_s(frame: Frame) -> float | None:
        """The scan's time per row (what the vibration lines are fitted over), on the
        same clock as the lines were learned (the source's own where it has one); None
        when the header says nothing of the scan itself (the time since the frame
        before bounds a scan, it does not time its rows)."""
        header = frame.header
        lasted = scan_lasted_s(header.shape, source_interval_s=header.source_interval_s, dwell_ns=header.dwell_ns,
                               scan_started_at_ns=header.scan_started_at_ns, acquired_at_ns=header.acquired_at_ns)
        return lasted / header.shape[0] if lasted else None

    def _tilt_fields(self, tilt: dict | None) -> dict:
        """``tilt``, the latest tilt measurement against this reference, carried by every
        estimate (the controller acts on each one once: by its ``tilt_seq``)."""
        if not self.measure_tilts or tilt is None or self.reference is None or tilt["reference_id"] != self.reference.id:
            return {}
        return {"alpha_deg": tilt["alpha_deg"], "beta_deg": tilt["beta_deg"], "tilt_confidence": tilt["confidence"],
                "tilt_seq": tilt["tilt_seq"], "tilt_scan_started_at_ns": tilt["scan_started_at_ns"],
                "tilt_frames": tilt["frames"], "tilt_sweep_s": tilt["sweep_s"],
                "tilt_source_interval_s": tilt["source_interval_s"],
                "tilt_reason": (tilt["reason"] or None) if tilt["confidence"] <= 0 else None,
                "tilt_uncertainty_deg": _finite_pair(tilt["alpha_uncertainty_deg"], tilt["beta_uncertainty_deg"])}

    def describe_reference(self) -> dict | None:
        """The reference as the protocol reports it, with its tilt sweep's progress."""
        if self.reference is None:
            return None
        teach = self.tilt_teach if self.tilt_teach and self.tilt_teach["reference_id"] == self.reference.id else None
        return {**self.reference.describe(), **({"tilt_teach": dict(teach)} if teach else {})}

    def report(self) -> dict:
        return {
            "reference": self.describe_reference(),
            "rotation": self.rotation,
            "measure_rotation": self.measure_rotation,
            "measure_tilts": self.measure_tilts,
            "tilt_reference": None if self.tilt_reference is None else {
                "reference_id": self.tilt_reference.reference_id, "frames": self.tilt_reference.frames,
                "alpha_deg": self.tilt_reference.estimate.alpha_deg, "beta_deg": self.tilt_reference.estimate.beta_deg},
            "last_tilt": self.last_tilt,
            "tilt_error": self.tilt_error,
            "precision": self.precision,
            "latest_frame_seq": self.latest.header.seq if self.latest else None,
            "last_estimate": self.last_estimate.model_dump() if self.last_estimate else None,
        }
