"""The estimator's core: the taught reference and frame -> motion, without sockets."""

from __future__ import annotations

import base64
import time
import uuid
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from semservo.estimation import MotionEstimator
from semservo.imagefiles import ImageFileError, read_image
from semservo.messages import MotionEstimate
from semservo.wire import Frame


class TeachError(ValueError):
    """A teach request that cannot be honoured; the previous reference is kept."""


class NotEnoughFrames(TeachError):
    """Fewer frames have arrived than the teach asks to average: ask again shortly."""


@dataclass
class Reference:
    id: str
    kind: str  # "frame", "image" or "mask"
    shape: tuple[int, int]
    pixel_size_nm: float | None
    taught_at_ns: int
    detail: dict[str, Any] = field(default_factory=dict)

    def describe(self) -> dict:
        return {"id": self.id, "kind": self.kind, "shape": list(self.shape), "pixel_size_nm": self.pixel_size_nm,
                "taught_at_ns": self.taught_at_ns, **self.detail}


def decode_upload(encoded: str) -> np.ndarray:
    """Pixels of a base64-encoded PNG or TIFF upload."""
    try:
        raw = base64.b64decode(encoded, validate=True)
    except (ValueError, TypeError) as error:
        raise TeachError(f"image_b64 is not base64: {error}") from None
    try:
        return read_image(raw)[0]
    except ImageFileError as error:
        raise TeachError(str(error)) from None


#: The smallest polygon a mask reference may be drawn from (square pixels): below this
#: the outline the mask is matched on is a few pixels of noise.
MIN_MASK_AREA_PX = 256

#: The most frames a reference may average (kept as the last received).
MAX_FRAMES_AVERAGED = 16


class EstimatorCore:
    def __init__(self, *, rotation: bool = True, precision: str = "full", fft_effort: str = "FFTW_MEASURE",
                 counters: Counter | None = None):
        self.rotation = rotation
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

    # -- teaching -------------------------------------------------------------
    def _install(self, pixels: np.ndarray, kind: str, pixel_size_nm: float | None, mask=None, **detail) -> dict:
        try:
            estimator = MotionEstimator(pixels, rotation=self.rotation, mask=mask, precision=self.precision,
                                        fft_effort=self.fft_effort)
        except ValueError as error:
            raise TeachError(str(error)) from None
        # Only now, with the new estimator built, is the old reference replaced.
        self.estimator = estimator
        self.reference = Reference(
            id=uuid.uuid4().hex[:12], kind=kind, shape=pixels.shape, pixel_size_nm=pixel_size_nm,
            taught_at_ns=time.time_ns(), detail=detail,
        )
        self.counters["references_taught"] += 1
        return self.reference.describe()

    def teach_latest(self, frames: int = 1) -> dict:
        """The latest frame becomes the reference, or the mean of the latest ``frames``
        (frame integration, as an SEM does for a clean image: it also averages out the
        stage vibration each single scan samples, which at x5000 is ~0.2 px; the stage
        must stand still over those frames)."""
        if self.latest is None:
            raise NotEnoughFrames("no frame has been received yet; is the image server running?")
        if not isinstance(frames, int) or not 1 <= frames <= self.recent.maxlen:
            raise TeachError(f"frames must be a whole number from 1 to {self.recent.maxlen}, got {frames!r}")
        chosen = list(self.recent)[-frames:]
        if len(chosen) < frames:
            raise NotEnoughFrames(f"only {len(chosen)} frames received so far; {frames} asked for averaging")
        shapes = {frame.pixels.shape for frame in chosen}
        if len(shapes) > 1 or len({frame.header.pixel_size_nm for frame in chosen}) > 1:
            raise TeachError("the scan changed during the frames to average; teach again")
        frame = chosen[-1]
        pixels = np.array(frame.pixels) if frames == 1 else np.mean([f.pixels for f in chosen], axis=0, dtype=np.float32)
        intervals = [f.header.source_interval_s for f in chosen]
        # On the source's clock (the fake lab's simulated time), when the reference was
        # scanned: what the simulator's truth for the taught pose is averaged over.
        scanned = [intervals[0][0], intervals[-1][1]] if all(intervals) else None
        return self._install(pixels, "frame", frame.header.pixel_size_nm, frame_seq=frame.header.seq,
                             source=frame.header.source, frames_averaged=frames, source_interval_s=scanned)

    def teach_image(self, pixels: np.ndarray, label: str = "upload") -> dict:
        if self.latest is not None and pixels.shape != self.latest.pixels.shape:
            rows, cols = self.latest.pixels.shape
            raise TeachError(f"image is {pixels.shape[1]} x {pixels.shape[0]}, the current scan is {cols} x {rows}")
        pixel_size = self.latest.header.pixel_size_nm if self.latest is not None else None
        return self._install(pixels, "image", pixel_size, label=label)

    def teach_mask(self, *, polygon=None, mask: np.ndarray | None = None) -> dict:
        """A mask reference (paper case 6) drawn on the latest frame's shape and levels."""
        if self.latest is None:
            raise TeachError("a mask is drawn on the live image: no frame has been received yet")
        if (polygon is None) == (mask is None):
            raise TeachError("give either polygon corner points or a mask image")
        if mask is not None and mask.shape != self.latest.pixels.shape:
            raise TeachError(f"mask is {mask.shape[1]} x {mask.shape[0]}, the current scan is "
                             f"{self.latest.pixels.shape[1]} x {self.latest.pixels.shape[0]}")
        try:
            shape_mask = [tuple(map(float, point)) for point in polygon] if polygon is not None else mask > 0
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
                             mask=shape_mask, **detail)

    def warm_up(self) -> None:
        """Compile the per-frame kernels now (numba compiles on first use, seconds when
        its on-disk cache is cold), so the first teach and estimate answer promptly."""
        rows, cols = np.mgrid[0:64, 0:64]
        texture = (np.sin(cols / 3.0) * np.cos(rows / 5.0) + np.sin((rows + cols) / 7.0)).astype(np.float32)
        estimator = MotionEstimator(texture, rotation=self.rotation, precision=self.precision,
                                    fft_effort="FFTW_ESTIMATE")
        estimator.estimate(np.roll(texture, 2, axis=1))

    def measure(self, rotation: bool | None) -> dict:
        """Measure rotation per frame or not (None: as configured)."""
        if rotation and not self.rotation:
            raise TeachError("rotation is off in this estimator's configuration (SEMSERVO_ESTIMATOR__ROTATION)")
        self.measure_rotation = self.rotation if rotation is None else bool(rotation)
        return {"rotation": self.measure_rotation}

    def clear(self) -> dict:
        had = self.reference is not None
        self.estimator = None
        self.reference = None
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
        motion = self.estimator.estimate(frame.pixels, rotation=self.measure_rotation and self.estimator.rotation)
        elapsed_ms = (time.perf_counter() - started) * 1e3
        now = time.time_ns()
        estimate = MotionEstimate(
            seq=frame.header.seq, reference_id=self.reference.id,
            dx_px=motion.dx, dy_px=motion.dy, rotation_deg=motion.rotation_deg,
            confidence=min(1.0, max(0.0, motion.confidence)), snr_db=motion.snr_db, filtered=motion.filtered,
            pixel_size_nm=frame.header.pixel_size_nm,
            frame_acquired_at_ns=frame.header.acquired_at_ns, frame_published_at_ns=frame.header.published_at_ns,
            frame_scan_started_at_ns=frame.header.scan_started_at_ns,
            frame_source_interval_s=frame.header.source_interval_s,
            published_at_ns=now, estimation_ms=elapsed_ms,
            latency_ms=(now - frame.header.published_at_ns) / 1e6,
        )
        self.counters["estimates"] += 1
        self.last_estimate = estimate
        return estimate

    def report(self) -> dict:
        return {
            "reference": self.reference.describe() if self.reference else None,
            "rotation": self.rotation,
            "measure_rotation": self.measure_rotation,
            "precision": self.precision,
            "latest_frame_seq": self.latest.header.seq if self.latest else None,
            "last_estimate": self.last_estimate.model_dump() if self.last_estimate else None,
        }
