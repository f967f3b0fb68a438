"""Estimator process: image server frames (latest only) -> core -> motion on PUB;
teach / clear / report on the control socket.

Run it with ``semservo service estimator``; settings ``SEMSERVO_ESTIMATOR__*``.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from semservo.config import Settings, connect
from semservo.imagefiles import ImageFileError, read_image
from semservo.logs import configure
from semservo.messages import MOTION_TOPIC
from semservo.service import ServiceRuntime
from semservo.transport import BadRequest, CommandError, ControlClient, FrameSubscriber, MessagePublisher
from services.estimator.core import EstimatorCore, NotEnoughFrames, TeachError, TiltSettings, decode_upload
from services.estimator.tilts import SweepFailed, TiltTracker, run_sweep

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
                        max_tilt_deg=config.tilt_max_deg, kernel_px=config.tilt_kernel_px, method=config.tilt_method)
    core = EstimatorCore(rotation=config.rotation and not args.no_rotation,
                         precision=args.precision or config.precision, fft_effort=config.fft_effort,
                         counters=runtime.counters, tilt=tilt)
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

    def taught(result: dict) -> dict:
        runtime.state = "running"
        log.info("taught reference %s (%s)", result["id"], result["kind"])
        return result

    def teach(args: dict) -> dict:
        tilts = args.pop("tilts", False)
        if not isinstance(tilts, bool):
            raise BadRequest("tilts must be true or false")
        if tilts and tracker.busy:
            raise CommandError("busy", "a focus sweep is running (tilts are being measured): stop the run first")
        result = _teach(args)
        if tilts:  # the taught pose's focus sweep, now, before anything moves
            try:
                with tracker.lock:
                    sweep, result_of_sweep = run_sweep(tracker.client(), core.next_sweep(), config.sweep_timeout_s)
                    result = core.teach_tilt(sweep, result_of_sweep["working_distances_um"],
                                             result_of_sweep["pixel_size_nm"])
            except SweepFailed as error:
                raise CommandError("sweep_failed", f"the reference image is taught, but its focus sweep failed: "
                                                   f"{error}") from None
            except TeachError as error:
                raise CommandError("no_tilt_reference", f"the reference image is taught, but not its tilts: "
                                                        f"{error}") from None
        return result

    def _teach(args: dict) -> dict:
        try:
            if "image_b64" in args:
                return taught(core.teach_image(decode_upload(args["image_b64"]), label=str(args.get("label", "upload"))))
            if "path" in args:
                if not isinstance(args["path"], str):
                    raise TeachError("path must be a file path (text)")
                try:
                    pixels, _ = read_image(Path(args["path"]))
                except ImageFileError as error:
                    raise TeachError(str(error)) from None
                return taught(core.teach_image(pixels, label=str(args["path"])))
            if "polygon" in args:
                return taught(core.teach_mask(polygon=args["polygon"]))
            if "mask_b64" in args:
                return taught(core.teach_mask(mask=decode_upload(args["mask_b64"])))
            return taught(core.teach_latest(frames=args.get("frames", 1)))
        except NotEnoughFrames as error:  # its own code: a caller may wait and ask again
            raise CommandError("not_enough_frames", str(error)) from None
        except TeachError as error:
            raise BadRequest(str(error)) from None

    def clear(_args: dict) -> dict:
        runtime.state = "idle"
        return core.clear()

    runtime.control.register("teach", teach)
    def measure(args: dict) -> dict:
        rotation, tilts = args.get("rotation"), args.get("tilts")
        for name, value in (("rotation", rotation), ("tilts", tilts)):
            if value is not None and not isinstance(value, bool):
                raise BadRequest(f"{name} must be true, false or null")
        try:
            result = core.measure(rotation, tilts)
        except TeachError as error:
            code = "no_tilt_reference" if tilts and "tilt reference" in str(error) else "bad_request"
            raise CommandError(code, str(error)) from None
        tracker.wake()
        return result

    runtime.control.register("clear", clear)
    runtime.control.register("measure", measure)
    runtime.control.register("report", lambda _args: core.report())
    runtime.details = lambda: {
        "reference": core.reference.describe() if core.reference else "none taught: publishing nothing",
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
    try:
        return runtime.run()
    finally:
        tracker.stop()
        motion.close()
        runtime.context.destroy(linger=0)  # closes what is still open: term() would wait on it


if __name__ == "__main__":
    raise SystemExit(main())
