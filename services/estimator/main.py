"""Estimator process: image server frames (latest only) -> core -> motion on PUB; the
commands (declared in :mod:`semservo.protocol.estimator`, answered by
:mod:`services.estimator.commands`) on the control socket.

Run it with ``semservo service estimator``; settings ``SEMSERVO_ESTIMATOR__*``.
"""

from __future__ import annotations

import argparse
import logging

from semservo.config import Settings, connect
from semservo.logs import configure
from semservo.messages import MOTION_TOPIC
from semservo.service import ServiceRuntime
from semservo.transport import ControlClient, FrameSubscriber, MessagePublisher
from services.estimator.commands import Estimator, handlers
from services.estimator.core import EstimatorCore, TiltSettings
from services.estimator.tilts import TiltTracker

log = logging.getLogger("estimator")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="semservo service estimator",
        description="Measure each frame's motion against the taught reference and publish it.",
    )
    parser.add_argument("--no-rotation", action="store_true", help="translation only")
    parser.add_argument("--precision", choices=["fast", "full"], help="sub-pixel fit resolution (default: settings)")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    settings = Settings()
    configure(settings.log_level)
    config = settings.estimator
    runtime = ServiceRuntime("estimator", settings, settings.bind(config.control_port))
    tilt = TiltSettings(depth_of_field_um=config.tilt_depth_of_field_um, centre_um=config.tilt_centre_um,
                        max_tilt_deg=config.tilt_max_deg, kernel_px=config.tilt_kernel_px, method=config.tilt_method,
                        teach_sweeps=config.tilt_teach_sweeps, focus_measure=config.tilt_focus_measure,
                        fine_teach_sweeps=config.tilt_fine_teach_sweeps)
    core = EstimatorCore(rotation=config.rotation and not args.no_rotation,
                         precision=args.precision or config.precision, fft_effort=config.fft_effort,
                         counters=runtime.counters, tilt=tilt, scan_averaged=config.scan_averaged,
                         vibration_lines=config.vibration_lines)
    imageserver_endpoint = connect(settings.imageserver.host, settings.imageserver.control_port)
    tracker = TiltTracker(core, lambda: ControlClient(imageserver_endpoint, timeout_s=5.0, retries=2),
                          timeout_s=config.sweep_timeout_s)
    core.warm_up()
    runtime.state = "idle"  # until a reference is taught
    frames_endpoint = connect(settings.imageserver.host, settings.imageserver.frames_port)
    frames = FrameSubscriber(frames_endpoint, max_message_bytes=settings.max_message_bytes,
                             context=runtime.context, counters=runtime.counters)
    motion = MessagePublisher(settings.bind(config.motion_port), MOTION_TOPIC, context=runtime.context)
    runtime.report_errors_from(lambda: frames.last_error or core.tilt_error)
    log.info("frames from %s, motion on %s", frames_endpoint, motion.endpoint)

    handlers.bind(runtime.control, Estimator(core, tracker))
    runtime.details = lambda: {
        "reference": core.describe_reference() or "none taught: publishing nothing",
        "last_latency_ms": core.last_estimate.latency_ms if core.last_estimate else None,
        "last_estimation_ms": core.last_estimate.estimation_ms if core.last_estimate else None,
        "last_snr_db": core.last_estimate.snr_db if core.last_estimate else None,
        "measure_tilts": core.measure_tilts,
        "last_tilt": core.last_tilt,
    }

    def on_frame() -> None:
        frame = frames.receive(timeout_s=0)
        if frame is None:
            return
        try:
            estimate = core.process(frame)
        except ValueError as error:
            runtime.error(str(error))
            return
        if estimate is not None:
            motion.publish(estimate)
            runtime.counters["motion_published"] = motion.sent

    runtime.add_reader(frames.socket, on_frame)
    tracker.start()

    def step() -> None:
        runtime.state = "running" if core.reference is not None else "idle"  # idle: publishing nothing

    try:
        return runtime.run(step)
    finally:
        tracker.stop()
        motion.close()
        runtime.context.destroy(linger=0)  # closes what is still open: term() would wait on it


if __name__ == "__main__":
    raise SystemExit(main())
