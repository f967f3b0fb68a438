"""semservo's loop in a lab script's own process, on the OpenFIBSEM microscope it holds.

A script that already drives its microscope through OpenFIBSEM keeps doing so; three
lines position it with semservo::

    positioner = Positioner(microscope, hfw_um=100, dwell_ns=1000)
    positioner.teach()                         # the view now is the target
    run = positioner.run(beam_shift_within_um=2)  # later: back to it, stage then beam shift

Inside are the same parts as the services, without sockets: the image source
(:class:`~semservo.openfibsem.OpenFibsemSource`), the estimator's core, the stage
service's core on the motion driver (:class:`~semservo.openfibsem.OpenFibsemMotion`,
every rule of the stage: travel and step per axis, stop, watchdog, the command log) and
the controller's core (the paper's law, eq. 30-37, and its run records), joined by
:class:`semservo.protocol.LocalPort`. Each iteration scans a frame after the last move
has settled, measures it against the reference, and moves.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

from semservo.control import CameraToStage
from semservo.errors import CommandError
from semservo.openfibsem.motion import OpenFibsemMotion
from semservo.openfibsem.source import OpenFibsemSource
from semservo.protocol import LocalPort
from semservo.protocol.controller import RunSettings
from semservo.wire import Frame, frame_header
from services.controller.core import ControllerCore
from services.estimator.commands import Estimator
from services.estimator.commands import handlers as estimator_handlers
from services.estimator.core import EstimatorCore
from services.stage.commands import handlers as stage_handlers
from services.stage.physical import PhysicalLimits, PhysicalStageCore


class Positioner:
    """Teach a view, then position the microscope back to it: semservo's estimator,
    controller and stage rules on an OpenFIBSEM ``microscope``, in this process.

    ``resolution``, ``dwell_ns``, ``hfw_um``, ``beam``: the scan (as
    :class:`~semservo.openfibsem.OpenFibsemSource`). ``camera``: the camera-to-stage
    transform (default: the image's axes, as :mod:`semservo.openfibsem.units` maps
    them). ``max_step_um``, ``travel``, ``beam_limit_um``, ``stage_move``: the stage's
    rules and the driver's options. ``runs_dir``: where run records go (none: kept in
    memory only). ``clock``: a simulated microscope's own clock (the tests'; none for a
    microscope).
    """

    def __init__(self, microscope: Any, *, resolution: tuple[int, int] = (512, 512), dwell_ns: float = 1000.0,
                 hfw_um: float = 100.0, beam: str = "electron", camera: CameraToStage | None = None,
                 max_step_um: float = 10.0, travel: dict[str, tuple[float, float]] | None = None,
                 beam_limit_um: float | None = None, stage_move: str = "stable", runs_dir: Path | None = None,
                 clock: Callable[[], float] | None = None):
        self.source = OpenFibsemSource(microscope=microscope, resolution=resolution, dwell_ns=dwell_ns,
                                       hfw_um=hfw_um, beam=beam, clock=clock)
        self.driver = OpenFibsemMotion(microscope, beam=beam, stage_move=stage_move, beam_limit_um=beam_limit_um)
        self.stage = PhysicalStageCore("openfibsem:in-process", open_driver=lambda _url: self.driver,
                                       physical=PhysicalLimits(max_step_um=max_step_um, travel=dict(travel or {})))
        if not self.stage.connect():
            raise RuntimeError(f"the microscope's stage and beam shift cannot be driven: {self.stage.last_error}")
        self.estimator = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE")
        # A scan may take seconds: the stage's watchdog must outlast one, and the
        # controller feeds it between scans.
        frame_s = self.frame_s = dwell_ns * 1e-9 * resolution[0] * resolution[1]
        self.controller = ControllerCore(LocalPort(stage_handlers, self.stage),
                                         estimator=LocalPort(estimator_handlers, Estimator(self.estimator)),
                                         camera=camera or CameraToStage(), runs_dir=runs_dir,
                                         watchdog_s=max(3.0, 4 * frame_s), name="openfibsem")
        self.seq = 0

    def frame(self) -> Frame:
        """One scan, as the image server would publish it."""
        image = self.source.acquire()
        self.seq += 1
        header = frame_header(image.pixels, seq=self.seq, acquired_at_ns=image.acquired_at_ns, source=self.source.name,
                              label=image.label, scan_started_at_ns=image.scan_started_at_ns,
                              source_interval_s=image.source_interval_s, **image.acquisition())
        return Frame(header, image.pixels)

    def teach(self, frames: int = 1) -> dict:
        """The view now (the mean of ``frames`` scans) becomes the target; returns the
        reference as the estimator describes it."""
        for _ in range(frames):
            self.estimator.process(self.frame())
        return self.estimator.teach_latest(frames)

    def run(self, *, timeout_s: float = 300.0, **settings: Any) -> dict:
        """Position back to the taught view: scan, measure, move, until the run ends
        (converged, failed with the reason, stopped). ``settings``: any
        :class:`~semservo.protocol.controller.RunSettings` field (``tolerance_px``,
        ``beam_shift_within_um``, ``max_move_um``, ...). Returns the run's record
        (``outcome``, every iteration, the stage's command log)."""
        reference = self.estimator.describe_reference()
        if reference is None:
            raise CommandError("no_reference", "teach a view first (Positioner.teach)")
        self.stage.rebase()  # the script may have moved the microscope itself since the last run
        # A run fails when no estimate comes for estimate_timeout_s: here one comes per
        # scan, so give a slow scan (or a busy computer) its time.
        settings.setdefault("estimate_timeout_s", min(600.0, max(30.0, 10 * self.frame_s)))
        self.controller.start(RunSettings(dofs=["x", "y"], **settings), reference)
        deadline = time.monotonic() + timeout_s
        try:
            while self.controller.state == "servoing":
                if time.monotonic() > deadline:
                    self.controller.stop(f"no end within {timeout_s:g} s")
                    break
                # A frame scanned before the last move settled shows the stage moving.
                wait_s = (self.controller.run.last_command_ns - time.time_ns()) / 1e9
                if wait_s > 0:
                    time.sleep(wait_s)
                estimate = self.estimator.process(self.frame())
                if estimate is not None:
                    self.controller.on_estimate(estimate)
                # After the estimate: a slow scan is not a silent estimator. Then the
                # watchdog's heartbeat, before the stage looks at it.
                self.controller.tick()
                self.stage.poll()
        except BaseException:
            self.controller.stop("the positioning loop was interrupted")
            raise
        return self.controller.record()

    def stop(self, reason: str = "stop requested") -> None:
        """Hold the stage and beam at once; nothing moves until :meth:`resume`."""
        self.controller.stop(reason)

    def resume(self) -> None:
        self.stage.resume()
