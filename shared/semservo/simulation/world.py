"""One physical world shared by the simulated devices, as in a real chamber: the piezo
stage (driven by the emulated NV 40/3) moves the sample, the simulated SEM images it.

Time is simulated: ``now()`` runs ``speedup`` times faster than the wall clock, so tests
can scan faster than real time with the same physics. A scan covers the interval it
takes in simulated time; the caller waits for it to end (stage commands sent meanwhile
land in the frame, as on the real instrument) and the frame is rendered from the pose
history. Thread-safe: the serial emulator and the scan server run in their own threads.
"""

from __future__ import annotations

import math
import threading
import time
import uuid
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from semservo.simulation.goniometer import LIMITS_DEG, Goniometer
from semservo.simulation.piezo import PiezoAxis
from semservo.simulation.sem import DEFAULT_APERTURE_UM, NOMINAL_WORKING_DISTANCE_MM, SEM, Pose, ScanSettings

#: Each channel starts at this voltage, about mid-travel, so the stage can move both ways.
HOME_VOLTAGE = 38.0


@dataclass(frozen=True)
class Preset:
    """One of the paper's experimental conditions (section IV-C)."""

    name: str
    scene: str
    magnification: float
    dwell_ns: float
    reference_dwell_ns: float | None = None  # high-quality reference taught slower
    unstable_levels: bool = False  # brightness and contrast change during the run
    mask_reference: bool = False
    description: str = ""
    #: The objective aperture and the nominal working distance set the beam half-angle,
    #: hence the depth of field (:class:`semservo.simulation.sem.SEM`).
    aperture_um: float = DEFAULT_APERTURE_UM
    working_distance_mm: float = NOMINAL_WORKING_DISTANCE_MM
    #: Where a scan focuses unless told: the working distance's offset (um) from the
    #: stage's reference surface, larger deeper (-10: the micropart's top).
    focus_um: float = -10.0


PRESETS = {
    preset.name: preset
    for preset in (
        Preset("optimal", "micropart", 1200, 720, description="720 ns/px at x1200 (case 1)"),
        Preset("noisy", "micropart", 1200, 180, description="fastest scan, 180 ns/px (case 2)"),
        Preset("high-magnification", "micropart", 5000, 360, description="x5000 at 360 ns/px (case 3)"),
        Preset("unstable", "micropart", 1200, 360, unstable_levels=True,
               description="brightness and contrast drift during the run (case 4)"),
        Preset("high-quality-reference", "micropart", 1200, 360, reference_dwell_ns=5800,
               description="reference at 5.8 us/px, run at 360 ns/px (case 5)"),
        Preset("mask-reference", "micropart", 1200, 720, mask_reference=True,
               description="a binary mask of the part as the reference (case 6)"),
        Preset("repeated-pattern", "chessboard", 1200, 180,
               description="calibration chessboard at 180 ns/px (case 7)"),
        # The paper's tilt regime: high magnification and a small depth of field (a large
        # aperture at a short working distance: beam half-angle 40 mrad, depth of field
        # 3.5 um), on a flat sample rich in texture, so that depth from focus can see a
        # tilt of a fraction of a degree across the field.
        Preset("tilts", "gold-on-carbon", 3000, 360, aperture_um=400.0, working_distance_mm=5.0, focus_um=0.0,
               description="x3000, small depth of field (400 um aperture at 5 mm), gold on carbon (tilts)"),
    )
}


def image_preset(preset: Preset, sample) -> Preset:
    """``preset`` with a real picture as its sample
    (:class:`semservo.simulation.sample_image.SampleImage`): its optics, dwell, levels and
    reference, but the picture's scale (the magnification whose scan has the picture's
    pixel, or a finer one where a frame would not fit; see ``default_magnification``) and
    focus on the picture's median height. Refused (SampleImageError) when the picture
    cannot give even that scan."""
    magnification = sample.default_magnification()
    sample.check_scan(magnification, 512, 512)
    return replace(preset, scene=f"image:{sample.name}", magnification=magnification,
                   focus_um=0.0 - sample.median_height_um + 0.0,
                   description=f"the {preset.name} preset's optics, with the picture {sample.name} as its sample "
                               f"in place of its {preset.scene} scene ({sample.pixel_um * 1000:.4g} nm/px, scanned at "
                               f"x{magnification:.4g})")


@dataclass
class Disturbances:
    """Thermal drift (um/s, simulated time) and vibration (sum of sinusoids)."""

    drift_um_per_s: tuple[float, float] = (0.002, -0.0015)
    vibration: tuple = ((7.0, 0.010, 0.3), (50.0, 0.006, 1.1), (93.0, 0.004, 2.0))  # (Hz, um, phase)
    #: Each vibration line's phase wanders by a random walk of this many radians per
    #: square root of a second, on each axis on its own (a line of finite width, as a
    #: mechanical resonance is); 0: steady tones. Another vibration than the default's,
    #: for checking what is fitted to steady tones (``bench/scan_averaged.py --wander``).
    phase_walk_rad_per_sqrt_s: float = 0.0
    walk_seed: int = 0
    _walks: list = field(default_factory=list, repr=False, compare=False)

    #: The random walk's time step (s): finer than a row of any preset's scan.
    WALK_STEP_S = 2e-4

    def _phase_walk(self, t: float) -> np.ndarray:
        """Each line's wandered phase at ``t`` on x and y (lines x 2, radians): a random
        walk drawn once (from ``walk_seed``) and extended as time goes on, interpolated."""
        steps = int(max(t, 0.0) / self.WALK_STEP_S) + 2
        while sum(len(block) for block in self._walks) < steps:
            rng = np.random.default_rng([self.walk_seed, len(self._walks)])
            block = rng.normal(0.0, self.phase_walk_rad_per_sqrt_s * math.sqrt(self.WALK_STEP_S),
                               (50_000, len(self.vibration), 2))
            start = self._walks[-1][-1] if self._walks else np.zeros((len(self.vibration), 2))
            self._walks.append(start + np.cumsum(block, axis=0))
        position = max(t, 0.0) / self.WALK_STEP_S
        index = int(position)
        block, within = divmod(index, 50_000)
        here = self._walks[block][within]
        following = self._walks[(index + 1) // 50_000][(index + 1) % 50_000]
        return here + (position - index) * (following - here)

    def offset(self, t: float, *, vibration: bool = True) -> tuple[float, float]:
        """The sample's offset at ``t``: drift, and the vibration unless told not to (where
        the sample rests, about which it vibrates)."""
        x = self.drift_um_per_s[0] * t
        y = self.drift_um_per_s[1] * t
        if not vibration:
            return x, y
        walk = self._phase_walk(t) if self.phase_walk_rad_per_sqrt_s > 0 else None
        for index, (frequency, amplitude, phase) in enumerate(self.vibration):
            wander_x, wander_y = (walk[index] if walk is not None else (0.0, 0.0))
            x += amplitude * math.sin(2 * math.pi * frequency * t + phase + wander_x)
            y += amplitude * math.cos(2 * math.pi * frequency * t + phase + index + wander_y)
        return x, y


#: The simulated rotation-and-tilt stage's travel (degrees).
ROTATION_STAGE_LIMITS_DEG = LIMITS_DEG


@dataclass
class World:
    preset: Preset = PRESETS["optimal"]
    speedup: float = 1.0
    seed: int = 2013
    disturbances: Disturbances = field(default_factory=Disturbances)
    clock: callable = time.monotonic
    #: A real picture as the sample (:mod:`semservo.simulation.sample_image`), under any
    #: preset's optics; None: the preset's own scene.
    sample_image: object | None = None

    def __post_init__(self):
        self.lock = threading.RLock()
        self.render_lock = threading.Lock()
        self._frozen_at: float | None = None
        self.started = self.clock()
        self.axes = {0: PiezoAxis("x"), 1: PiezoAxis("y"), 2: PiezoAxis("x")}
        for axis in self.axes.values():
            axis.command(HOME_VOLTAGE, -1e6)
        self.home_um = {channel: axis.position(0.0) for channel, axis in self.axes.items()}
        self.goniometer = Goniometer()  # the simulated rotation-and-tilt stage
        # Which world this is: truths measured across a restart of the simulator compare
        # two different worlds, and must be refused rather than computed.
        self.id = uuid.uuid4().hex[:12]
        self.base_preset = self.preset
        if self.sample_image is not None:
            self.preset = image_preset(self.preset, self.sample_image)
        self.sem = SEM.for_preset(self.preset, self.seed, self.sample_image)
        self.rng = np.random.default_rng(self.seed)
        self.frames = 0

    def now(self) -> float:
        """Simulated seconds since the world started (standing still while a sped-up
        world renders a frame, see :meth:`scan`)."""
        frozen = self._frozen_at
        if frozen is not None:
            return frozen
        return (self.clock() - self.started) * self.speedup

    # -- the stage ---------------------------------------------------------------
    def set_voltage(self, channel: int, voltage: float, t: float | None = None) -> None:
        with self.lock:
            self.axes[channel].command(voltage, self.now() if t is None else t)

    def voltage(self, channel: int) -> float:
        with self.lock:
            return self.axes[channel].voltage

    def set_rotation_stage(self, **angles: float) -> dict[str, float]:
        """Send the simulated rotation stage (rotation about the beam, two tilts) towards
        these angles (degrees, within :data:`ROTATION_STAGE_LIMITS_DEG`; anything else is
        refused whole). It gets there at its own speed, with backlash
        (:mod:`semservo.simulation.goniometer`). Returns the targets."""
        with self.lock:
            return self.goniometer.command(self.now(), **angles)

    def halt_rotation_stage(self) -> dict[str, float]:
        with self.lock:
            self.goniometer.halt(self.now())
            return self.goniometer.targets()

    @property
    def rotation_stage(self) -> dict[str, float]:
        """Where the rotation stage is now (degrees)."""
        with self.lock:
            return self.goniometer.angles(self.now())

    def rotation_stage_settles_in_s(self) -> float:
        """Wall seconds until the rotation stage reaches its targets (0 when there)."""
        with self.lock:
            return max(self.goniometer.arrival() - self.now(), 0.0) / self.speedup

    def pose(self, t: float | None = None, *, vibration: bool = True) -> Pose:
        """The true pose at simulated time ``t``: stage displacement from home, drift and
        vibration (without it: where the sample rests), and the rotation stage."""
        with self.lock:
            t = self.now() if t is None else t
            drift_x, drift_y = self.disturbances.offset(t, vibration=vibration)
            return Pose(
                x_um=self.axes[0].position(t) - self.home_um[0] + drift_x,
                y_um=self.axes[1].position(t) - self.home_um[1] + drift_y,
                z_um=self.axes[2].position(t) - self.home_um[2],
                **self.goniometer.angles(t),
            )

    # -- the SEM -------------------------------------------------------------------
    def set_preset(self, preset: Preset) -> None:
        """Image under another of the paper's conditions (the sample image, if any, stays
        the sample). Waits for a frame being rendered with the old SEM."""
        chosen = image_preset(preset, self.sample_image) if self.sample_image is not None else preset
        with self.lock, self.render_lock:
            self.base_preset, self.preset = preset, chosen
            self.sem = SEM.for_preset(chosen, self.seed, self.sample_image)

    def levels(self, t: float, settings: ScanSettings) -> ScanSettings:
        """Brightness and contrast as they are at ``t`` (the unstable preset drifts)."""
        if not self.preset.unstable_levels:
            return settings
        return replace(settings, contrast=settings.contrast * (1 + 0.35 * math.sin(2 * math.pi * t / 9.0)),
                       brightness=settings.brightness + 0.12 * math.sin(2 * math.pi * t / 13.0 + 1))

    def scan(self, settings: ScanSettings, *, wait: bool = True) -> tuple[np.ndarray, float, float]:
        """Acquire one frame starting now; returns (pixels, start, end) in simulated s.

        With ``wait`` the call returns when the scan would have ended (frame time /
        speedup of wall time), so stage moves during the scan are in the frame.
        """
        start = self.now()
        end = start + settings.frame_time_s
        if wait:
            remaining = (end - self.now()) / self.speedup
            if remaining > 0:
                time.sleep(remaining)
        line = settings.line_time_s
        active = settings.cols * (settings.dwell_ns + settings.pixel_dead_ns) * 1e-9
        line_start = [self.pose(start + row * line) for row in range(settings.rows)]
        line_end = [self.pose(start + row * line + active) for row in range(settings.rows)]
        rendering_since = self.clock()
        if self.speedup > 1:
            # Simulated time stands still while the simulator computes: a real scan
            # generator has no render time, and a sped-up clock would otherwise turn
            # 20 ms of arithmetic into a long pause between frames.
            with self.lock:
                self._frozen_at = self.now()
        try:
            # The stage stays free while the SEM renders (its own lock), so serial
            # commands are not delayed by the simulator's arithmetic.
            with self.render_lock:
                pixels = self.sem.render(self.levels(start, settings), line_start, line_end, self.rng)
                self.frames += 1
        finally:  # a failed render must not leave simulated time standing still for good
            if self.speedup > 1:
                with self.lock:
                    self.started += self.clock() - rendering_since
                    self._frozen_at = None
        return pixels, start, end

    def describe(self) -> dict:
        return {"world_id": self.id, "preset": asdict(self.preset), "speedup": self.speedup, "frames": self.frames,
                "sample_image": self.sample_image.describe() if self.sample_image is not None else None,
                "rotation_stage": self.rotation_stage, "rotation_stage_targets": self.goniometer.targets()}
