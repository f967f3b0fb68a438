"""The image server's core: pace a source at a frame rate and number its frames.

No sockets here: :meth:`ImageServerCore.due` tells the main loop when the next frame
is due and :meth:`ImageServerCore.next_frame` hands it the frame to publish.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from services.imageserver.sources import AcquiredImage, FrameSource, NotReady


@dataclass
class Pacer:
    """Deadlines at a fixed rate on the monotonic clock, without drift.

    A consumer that falls more than one period behind (a slow disk, a stall) resumes
    from now rather than bursting frames to catch up.
    """

    fps: float
    next_due: float | None = None

    def seconds_until_due(self, now: float) -> float:
        if self.next_due is None:
            return 0.0
        return max(0.0, self.next_due - now)

    def advance(self, now: float) -> None:
        period = 1.0 / self.fps
        if self.next_due is None or now - self.next_due > period:
            self.next_due = now + period
        else:
            self.next_due += period


@dataclass
class FreezeWatch:
    """Tells when a source that should be producing frames has gone silent: longer than
    ``min_silence_s`` and than ``factor`` times the typical interval between its frames
    (a slow scan is not a frozen one)."""

    min_silence_s: float = 5.0
    factor: float = 5.0
    first_frame_grace_s: float = 30.0  # a source's first frame may take long (a cold simulator, a slow scan)
    last_at: float | None = None
    typical_s: float | None = None

    def frame(self, now: float) -> None:
        if self.last_at is not None:
            interval = now - self.last_at
            self.typical_s = interval if self.typical_s is None else 0.8 * self.typical_s + 0.2 * interval
        self.last_at = now

    def silent_for(self, now: float, started: float) -> float | None:
        """Seconds without a frame when that is too long (from ``started`` before the
        first frame), else None."""
        since = now - (self.last_at if self.last_at is not None else started)
        limit = max(self.min_silence_s, self.factor * (self.typical_s or 0.0))
        if self.last_at is None:
            limit = max(limit, self.first_frame_grace_s)
        return since if since > limit else None


class ImageServerCore:
    def __init__(self, source: FrameSource, *, fps: float):
        if fps <= 0:
            raise ValueError(f"fps must be positive, got {fps}")
        self.source = source
        self.pacer = Pacer(fps)
        self.seq = 0
        self.exhausted = False
        self.waiting_for_source = False

    def set_fps(self, fps: float) -> None:
        if not 0 < fps <= 10_000:
            raise ValueError(f"fps must be in (0, 10000], got {fps}")
        self.pacer = Pacer(fps, self.pacer.next_due)

    def seconds_until_due(self, now: float | None = None) -> float | None:
        """Seconds until the next frame is due; None when there is nothing to do until
        the source says it has a frame (its ``notify``), or once it is exhausted. A source
        that had nothing ready is asked again when it says (``wake_in_s``: e.g. a
        watched file's settle time), never on a short poll."""
        if self.exhausted:
            return None
        due = self.pacer.seconds_until_due(time.monotonic() if now is None else now)
        if not self.waiting_for_source:
            return due
        wake_in_s = getattr(self.source, "wake_in_s", None)
        hint = wake_in_s() if callable(wake_in_s) else None
        return None if hint is None else max(due, hint)

    def next_frame(self, now: float | None = None) -> tuple[int, AcquiredImage] | None:
        """The (sequence number, image) to publish now, or None if none is due."""
        now = time.monotonic() if now is None else now
        if self.exhausted or self.pacer.seconds_until_due(now) > 0:
            return None
        try:
            image = self.source.acquire()
        except NotReady:  # a background source has no new frame yet: try again soon
            self.waiting_for_source = True
            return None
        self.waiting_for_source = False
        if image is None:
            self.exhausted = True
            return None
        self.pacer.advance(now)
        seq = self.seq
        self.seq += 1
        return seq, image
