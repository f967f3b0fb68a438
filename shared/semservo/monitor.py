"""Watching a frame stream: rate, latency from publish to receipt, and header checks.

Used by ``semservo up`` to show that frames flow and by ``semservo frames``.
"""

from __future__ import annotations

import time
from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np

from semservo.wire import Frame


def acquisition_text(header) -> str:
    """Pixel size, magnification and dwell as far as the frame knows them."""
    parts = [f"{header.pixel_size_nm:.1f} nm/px" if header.pixel_size_nm else "pixel size unknown"]
    if header.magnification:
        parts.append(f"x{header.magnification:g}")
    if header.dwell_ns:
        parts.append(f"{header.dwell_ns:g} ns/px")
    if header.working_distance_mm:
        parts.append(f"WD {header.working_distance_mm:g} mm")
    if header.high_voltage_kv:
        parts.append(f"{header.high_voltage_kv:g} kV")
    if header.detector:
        parts.append(header.detector)
    if header.data_bar_rows:
        parts.append(f"data bar {header.data_bar_rows} rows cropped")
    return ", ".join(parts) + ", "


@dataclass
class FrameStats:
    """Running statistics over the frames seen, with a window for rates and latency."""

    window: int = 200
    frames: int = 0
    sequence_gaps: int = 0
    first: Frame | None = None
    last: Frame | None = None
    _arrivals: deque = field(default_factory=deque)
    _latencies_ms: deque = field(default_factory=deque)

    def add(self, frame: Frame, received_at_ns: int | None = None) -> None:
        received_at_ns = time.time_ns() if received_at_ns is None else received_at_ns
        if self.last is not None and frame.header.seq != self.last.header.seq + 1:
            self.sequence_gaps += 1
        self.first = self.first or frame
        self.last = frame
        self.frames += 1
        self._arrivals.append(time.monotonic())
        self._latencies_ms.append((received_at_ns - frame.header.published_at_ns) / 1e6)
        while len(self._arrivals) > self.window:
            self._arrivals.popleft()
            self._latencies_ms.popleft()

    @property
    def fps(self) -> float:
        if len(self._arrivals) < 2:
            return 0.0
        span = self._arrivals[-1] - self._arrivals[0]
        return (len(self._arrivals) - 1) / span if span > 0 else 0.0

    def latency_ms(self, percentile: float) -> float:
        return float(np.percentile(self._latencies_ms, percentile)) if self._latencies_ms else float("nan")

    def summary(self, counters: Counter | None = None) -> str:
        if self.last is None:
            return "no frames yet"
        header = self.last.header
        rows, cols = header.shape
        text = (
            f"{self.frames} frames, {self.fps:.1f} fps, seq {header.seq}, {cols}x{rows} {header.dtype}, "
            + acquisition_text(header)
            + f"source {header.source}"
            + (f" ({header.label})" if header.label else "")
            + f", latency p50 {self.latency_ms(50):.2f} ms p99 {self.latency_ms(99):.2f} ms"
        )
        dropped = {key: value for key, value in (counters or {}).items() if key.startswith("dropped_")}
        if dropped:
            text += f", dropped {dropped}"
        return text
