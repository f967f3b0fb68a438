"""A worked example of an image-source adapter: a "microscope" whose API hands out
frames of a drifting test pattern.

It stands where a lab's adapter for its vendor's API would stand (Thermo Fisher's
AutoScript, Zeiss's SmartSEM API, TESCAN's SharkSEM...): the pattern generator below is
the only part a real adapter replaces with calls to the instrument. Run the system on it:

    SEMSERVO_IMAGESERVER__SOURCE=adapter \\
    SEMSERVO_IMAGESERVER__ADAPTER=examples.adapters.pattern_sem:PatternSEM \\
    SEMSERVO_IMAGESERVER__ADAPTER_OPTIONS='{"pixel_size_nm": 50, "drift_px_per_frame": 0.25}' \\
    ./dev up
"""

from __future__ import annotations

import time

import numpy as np

from semservo.instruments import AcquiredImage, ImageSourceAdapter, NotSupported, SourceUnavailable


class PatternSEM(ImageSourceAdapter):
    """Frames of a textured pattern that drifts ``drift_px_per_frame`` to the right per
    frame; ``fail_every`` > 0 makes every n-th scan fail, as a real instrument's may. Out
    of focus (the working distance away from ``focus_mm``) the pattern blurs, a pixel of
    blur per ``depth_of_field_um``: with :meth:`set_working_distance`, the image server
    serves focus sweeps from it (the tilt measurement's)."""

    name = "pattern-sem"

    def __init__(self, *, rows: int = 256, cols: int = 256, pixel_size_nm: float = 50.0, dwell_ns: float = 200.0,
                 drift_px_per_frame: float = 0.0, fail_every: int = 0, seed: int = 7, focus_mm: float = 10.0,
                 depth_of_field_um: float = 2.0):
        super().__init__(rows=rows, cols=cols, pixel_size_nm=pixel_size_nm, dwell_ns=dwell_ns,
                         drift_px_per_frame=drift_px_per_frame, fail_every=fail_every, seed=seed, focus_mm=focus_mm,
                         depth_of_field_um=depth_of_field_um)
        self.focus_mm, self.depth_of_field_um = focus_mm, depth_of_field_um
        rng = np.random.default_rng(seed)
        # The "sample": smooth blobs at several scales, as SEM texture is.
        spectrum = np.fft.fft2(rng.standard_normal((rows, cols)))
        frequency = np.hypot(*np.meshgrid(np.fft.fftfreq(rows), np.fft.fftfreq(cols), indexing="ij"))
        self.sample_spectrum = spectrum / (0.02 + frequency) ** 1.5
        self.frequency = frequency
        self.rows, self.cols = rows, cols
        self.pixel_size_nm, self.dwell_ns = pixel_size_nm, dwell_ns
        self.drift, self.fail_every = drift_px_per_frame, fail_every
        self.working_distance_mm = 10.0
        self.scans = 0

    def acquire(self) -> AcquiredImage:
        self.scans += 1
        if self.fail_every and self.scans % self.fail_every == 0:
            raise SourceUnavailable(f"scan {self.scans} failed (the instrument's API raised)")
        started = time.time_ns()
        shift = self.drift * self.scans
        phase = np.exp(-2j * np.pi * np.fft.fftfreq(self.cols)[None, :] * shift)  # a sub-pixel shift, exactly
        blur_px = abs(self.working_distance_mm - self.focus_mm) * 1000 / self.depth_of_field_um
        defocus = np.exp(-2 * (np.pi * blur_px * self.frequency) ** 2)  # a Gaussian probe, wider out of focus
        image = np.fft.ifft2(self.sample_spectrum * phase * defocus).real
        image = (image - image.min()) / (np.ptp(image) or 1.0) * 60000
        return AcquiredImage(
            pixels=image.astype(np.uint16), acquired_at_ns=time.time_ns(), scan_started_at_ns=started,
            pixel_size_nm=self.pixel_size_nm, dwell_ns=self.dwell_ns, working_distance_mm=self.working_distance_mm,
            detector="SE", instrument="example pattern SEM", label=f"scan {self.scans}",
        )

    def set_scan(self, *, dwell_ns: float | None = None, magnification: float | None = None) -> dict:
        if magnification is not None:
            raise NotSupported("the pattern SEM has one magnification")
        if dwell_ns is not None:
            if not 10 <= dwell_ns <= 100_000:
                raise ValueError(f"dwell {dwell_ns:g} ns is outside 10..100000 ns")
            self.dwell_ns = dwell_ns
        return {"dwell_ns": self.dwell_ns}

    def set_working_distance(self, working_distance_mm: float) -> float:
        self.working_distance_mm = working_distance_mm
        return self.working_distance_mm
