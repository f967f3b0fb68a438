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
from semservo.transport import BadRequest, CommandError, FrameSubscriber, MessagePublisher
from services.estimator.core import EstimatorCore, NotEnoughFrames, TeachError, decode_upload

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
    core = EstimatorCore(rotation=config.rotation and not args.no_rotation,
                         precision=args.precision or config.precision, fft_effort=config.fft_effort,
                         counters=runtime.counters)
    core.warm_up()
    runtime.state = "idle"  # until a reference is taught
    frames_endpoint = connect(settings.imageserver.host, settings.imageserver.frames_port)
    frames = FrameSubscriber(frames_endpoint, max_message_bytes=settings.max_message_bytes,
                             context=runtime.context, counters=runtime.counters)
    motion = MessagePublisher(settings.bind(config.motion_port), MOTION_TOPIC, context=runtime.context)
    runtime.report_errors_from(lambda: frames.last_error)
    log.info("frames from %s, motion on %s", frames_endpoint, motion.endpoint)

    def taught(result: dict) -> dict:
        runtime.state = "running"
        log.info("taught reference %s (%s)", result["id"], result["kind"])
        return result

    def teach(args: dict) -> dict:
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
        rotation = args.get("rotation")
        if rotation is not None and not isinstance(rotation, bool):
            raise BadRequest("rotation must be true, false or null")
        try:
            return core.measure(rotation)
        except TeachError as error:
            raise BadRequest(str(error)) from None

    runtime.control.register("clear", clear)
    runtime.control.register("measure", measure)
    runtime.control.register("report", lambda _args: core.report())
    runtime.details = lambda: {
        "reference": core.reference.describe() if core.reference else "none taught: publishing nothing",
        "last_latency_ms": core.last_estimate.latency_ms if core.last_estimate else None,
        "last_estimation_ms": core.last_estimate.estimation_ms if core.last_estimate else None,
        "last_snr_db": core.last_estimate.snr_db if core.last_estimate else None,
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
    try:
        return runtime.run()
    finally:
        motion.close()
        runtime.context.destroy(linger=0)  # closes what is still open: term() would wait on it


if __name__ == "__main__":
    raise SystemExit(main())
