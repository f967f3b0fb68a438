"""OpenFIBSEM's DemoMicroscope, seeing a sample: its frames rendered by semservo's
simulated SEM (:mod:`semservo.simulation.sem`) at the demo's own stage position and beam
shift, so a closed loop through fibsem's calls can be run, and judged by the truth.

The DemoMicroscope moves its stage and its beam shift as told, but its frames do not
follow them (each is noise with a label). :class:`SimulatedDemoFrames` replaces its
frame generator: each ``acquire_image`` scans the simulated sample (the micro-part of the
paper's *optimal* condition by default) over the field the image settings ask for
(``hfw`` / resolution is the pixel size, as the demo's metadata says), at the pose the
demo's stage and beam shift give it, plus the simulated lab's drift and vibration on a
simulated clock that advances by each scan's time.

The physics is written here, apart from :mod:`semservo.openfibsem.units` (what the
driver assumes), so a sign the two disagree on shows as a run that diverges:

* ``stable_move(dx, dy)`` moves the field of view over the sample by dx to the right
  and dy up (the view's y: fibsem's own inverse of its pre-tilt correction, from the
  stage's y and z), so the content moves by (-dx, +dy), x right and y down;
* ``beam_shift(dx, dy)`` moves the content by (+dx, -dy).

These are the signs OpenFIBSEM's own alignment acts on (``fibsem.alignment``: a content
displacement (dx right, dy down) is corrected by ``stable_move(dx, -dy)`` or
``beam_shift(-dx, dy)``); its alignment converges on this demo (``bench/openfibsem.py``),
which checks them apart from semservo's conversion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semservo.config import SCREEN_WIDTH_PX, SCREEN_WIDTH_UM
from semservo.simulation.sem import SEM, Pose, ScanSettings
from semservo.simulation.world import PRESETS, Disturbances


#: Blur stacks of the simulated sample, per (preset, seed): shared by every demo of a process.
_STACKS: dict[tuple[str, int], dict] = {}


@dataclass
class Scan:
    """One rendered frame: its interval on the simulated clock (s), the scan, and how far
    the stage and beam had moved the content (um, x right, y down; drift aside)."""

    start_s: float
    end_s: float
    settings: ScanSettings
    content_um: tuple[float, float] = (0.0, 0.0)


class SimulatedDemoFrames:
    """Installs itself on a ``DemoMicroscope``: its frames become simulated SEM scans of
    a sample carried by its stage, seen through its beam shift.

    ``clock`` is the simulated time (s); pass it to the image source
    (:class:`semservo.openfibsem.OpenFibsemSource`'s ``clock``) so each frame's
    ``source_interval_s`` is its scan, as the fake lab's are. :meth:`true_pose` is the
    truth a run is judged by.
    """

    def __init__(self, microscope, *, preset: str = "optimal", seed: int = 2013, disturbances: bool = True,
                 stage_play_um: float = 0.0):
        from fibsem.structures import BeamType

        self.microscope = microscope
        self.preset = PRESETS[preset]
        self.sem = SEM.for_preset(self.preset, seed)
        # The sample rasterized and blurred once per process (seconds of work; read only).
        self.stack_key = (preset, seed)
        self.sem._stacks = dict(_STACKS.get(self.stack_key, {}))
        self.rng = np.random.default_rng(seed)
        self.disturbances = Disturbances() if disturbances else Disturbances((0.0, 0.0), ())
        self.electron = BeamType.ELECTRON
        self.t = 0.0
        self.scans: list[Scan] = []
        from semservo.openfibsem.session import at_working_height

        at_working_height(microscope)  # a demo's stage starts at the floor of its z range
        position = microscope.get_stage_position()
        self.origin = (float(position.x), float(position.y), float(position.z))
        self._requested = None
        original = microscope.acquire_image

        def acquire_image(image_settings=None, beam_type=None):
            # The demo does not hand its frame generator the scan it was asked for: keep it.
            self._requested = image_settings or microscope.get_imaging_settings(beam_type)
            return original(image_settings=image_settings, beam_type=beam_type)

        microscope.acquire_image = acquire_image
        # A stage is not exact: each move lands within its play (a Gaussian, per axis, in
        # the image plane) while its encoders read where it was sent. 0: exact, as the demo.
        self.stage_play_um = float(stage_play_um)
        self.landing_error_um = np.zeros(2)
        self.play_rng = np.random.default_rng(seed + 1)
        move_relative = microscope.move_stage_relative

        def move_stage_relative(position):
            moved = move_relative(position)
            if self.stage_play_um > 0 and any(getattr(position, axis) for axis in ("x", "y", "z")):
                self.landing_error_um += self.play_rng.normal(0.0, self.stage_play_um, 2)
            return moved

        microscope.move_stage_relative = move_stage_relative
        microscope.use_image_sequence = True
        microscope._generate_next_image = self._render
        # The image source finds the simulated clock here (its frames' source_interval_s).
        microscope.semservo_clock = self.clock

    def clock(self) -> float:
        """Simulated seconds (advanced by each scan)."""
        return self.t

    def content_um(self) -> tuple[float, float]:
        """How far the demo's stage and beam shift have moved the content from where it
        was at install, in um (x right, y down as displayed)."""
        position = self.microscope.get_stage_position()
        x0, y0, z0 = self.origin
        view_up_m = float(self.microscope._inverse_y_corrected_stage_movement(
            dy=float(position.y) - y0, dz=float(position.z) - z0, beam_type=self.electron))
        shift = self.microscope.get_beam_shift(self.electron)
        right_m = -(float(position.x) - x0) + float(shift.x)
        down_m = view_up_m - float(shift.y)
        return right_m * 1e6 + self.landing_error_um[0], down_m * 1e6 + self.landing_error_um[1]

    def pose(self, t: float, content_um: tuple[float, float]) -> Pose:
        """The pose at ``t`` of content moved by ``content_um`` (drift and vibration added)."""
        drift_x, drift_y = self.disturbances.offset(t)
        return Pose(x_um=content_um[0] + drift_x, y_um=content_um[1] + drift_y)

    def true_pose(self, scans: list[Scan]) -> np.ndarray:
        """The content's mean pose (um) over these scans: what their frames show (the
        stage and beam where each scan saw them, the drift and vibration over it)."""
        poses = [np.array(scan.content_um) + np.mean([self.disturbances.offset(t)
                                                      for t in np.linspace(scan.start_s, scan.end_s, 32)], axis=0)
                 for scan in scans]
        return np.mean(poses, axis=0)

    def scan_settings(self, rows: int, cols: int) -> ScanSettings:
        requested = self._requested
        hfw_m = float(requested.hfw)
        # P = D / G (eq. 43) for the pixel size hfw / columns, as the demo's metadata says.
        magnification = SCREEN_WIDTH_UM * 1e-6 * SCREEN_WIDTH_PX / hfw_m
        return ScanSettings(dwell_ns=float(requested.dwell_time) * 1e9, magnification=magnification, rows=rows,
                            cols=cols, working_distance_um=self.preset.focus_um)

    def _render(self, beam_type, output_shape, dtype) -> np.ndarray:
        rows, cols = output_shape
        settings = self.scan_settings(rows, cols)
        start = self.t
        line = settings.line_time_s
        active = cols * (settings.dwell_ns + settings.pixel_dead_ns) * 1e-9
        # fibsem's calls block: the stage and the beam stand still while the demo scans.
        content = self.content_um()
        line_start = [self.pose(start + row * line, content) for row in range(rows)]
        line_end = [self.pose(start + row * line + active, content) for row in range(rows)]
        pixels = self.sem.render(settings, line_start, line_end, self.rng)
        _STACKS[self.stack_key] = self.sem._stacks
        self.t = start + settings.frame_time_s
        self.scans.append(Scan(start, self.t, settings, content))
        self.t += 1e-3  # the next scan starts a moment later
        return pixels.astype(dtype, copy=False)
