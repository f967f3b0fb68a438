"""Controller process: motion (SUB, from the estimator) -> core -> stage service (REQ).

Commands: ``start`` {settings...} (teaches nothing: the estimator's current reference is
the target), ``stop`` {reason}, ``status``, ``run`` {id?} (the active or last run's record,
or a finished one's by id), ``health``. At start it finishes the runs a killed
controller left (``ControllerCore.recover``). Events on the status PUB socket (topic ``controller``): ``status`` and
``iteration``.

Run it with ``semservo service controller``; settings ``SEMSERVO_CONTROLLER__*``.
"""

from __future__ import annotations

import argparse
import logging

import pydantic

from semservo.config import Settings, connect
from semservo.control import CameraToStage
from semservo.logs import configure
from semservo.messages import CONTROLLER_TOPIC, MOTION_TOPIC, ControllerEvent, MotionEstimate
from semservo.service import ServiceRuntime
from semservo.transport import BadRequest, CommandError, ControlClient, MessagePublisher, MessageSubscriber, ServiceUnavailable
from services.controller.core import ControllerCore, RunSettings

log = logging.getLogger("controller")


class ServicePort:
    """A port onto another service's control socket (lazy pirate, short timeouts: the
    loop must not stall on a dead peer)."""

    def __init__(self, client: ControlClient):
        self.client = client

    def request(self, command: str, args: dict | None = None) -> dict:
        return self.client.request(command, **(args or {}))


def build_parser() -> argparse.ArgumentParser:
    return argparse.ArgumentParser(
        prog="semservo service controller",
        description="Drive the stage until the current image matches the taught one (paper eq. 30-37).",
    )


def main(argv: list[str] | None = None) -> int:
    build_parser().parse_args(argv)
    settings = Settings()
    configure(settings.log_level)
    config = settings.controller
    runtime = ServiceRuntime("controller", settings, settings.bind(config.control_port))
    runtime.state = "idle"
    events = MessagePublisher(settings.bind(config.status_port), CONTROLLER_TOPIC, context=runtime.context)
    timeout = min(settings.request_timeout_s, 1.0)
    stage_client = ControlClient(connect(settings.stage.host, settings.stage.control_port), timeout_s=timeout,
                                 retries=2, context=runtime.context)
    estimator_client = ControlClient(connect(settings.estimator.host, settings.estimator.control_port),
                                     timeout_s=timeout, retries=2, context=runtime.context)
    for client in (stage_client, estimator_client):
        # A request waiting on a dead peer is abandoned as soon as a stop is asked for.
        client.cancelled = lambda: runtime.stopping

    def publish(kind: str, data: dict) -> None:
        events.publish(ControllerEvent(kind=kind, run_id=core.run and core.run["id"], data=data))

    core = ControllerCore(
        ServicePort(stage_client), estimator=ServicePort(estimator_client),
        camera=CameraToStage(tuple(config.axis_signs), config.orientation_deg, config.rotation_sign),
        runs_dir=config.runs_dir, watchdog_s=config.watchdog_s, publish=publish,
    )
    motion = MessageSubscriber(connect(settings.estimator.host, settings.estimator.motion_port), MOTION_TOPIC,
                               MotionEstimate, context=runtime.context, counters=runtime.counters)
    runtime.report_errors_from(lambda: motion.last_error)

    def start(args: dict) -> dict:
        try:
            run_settings = RunSettings.model_validate(args)
        except pydantic.ValidationError as error:
            first = error.errors()[0]
            raise BadRequest(f"{'.'.join(map(str, first['loc'])) or 'settings'}: {first['msg']}") from None
        if core.state == "servoing":
            raise CommandError("busy", f"run {core.run['id']} is active; stop it first")
        try:
            # Longer than the loop's 1 s: an estimator busy planning a new reference's FFTs
            # answers late, but answers.
            reference = estimator_client.request("report", timeout_s=5.0)["reference"]
        except (ServiceUnavailable, CommandError) as error:
            raise CommandError("estimator_unavailable", f"cannot ask the estimator for its reference: {error}") from None
        if not reference:
            raise CommandError("no_reference", "teach a reference first: the estimator has none")
        try:
            return core.start(run_settings, reference["id"])
        except ValueError as error:
            raise BadRequest(str(error)) from None
        except CommandError as error:
            raise CommandError(f"stage_{error.code}", f"the stage refused to start a run: {error.message}") from None
        except ServiceUnavailable as error:
            raise CommandError("stage_unavailable", f"the stage service is unreachable: {error}") from None

    runtime.control.register("start", start)
    runtime.control.register("stop", lambda args: core.stop(str(args.get("reason", "stop requested"))))
    runtime.control.register("status", lambda _args: core.status())
    def run(args: dict) -> dict:
        run_id = args.get("id")
        if run_id is None:
            return core.record()
        if not isinstance(run_id, str):
            raise BadRequest("id must be a run id (text)")
        record = core.stored(run_id)
        if record is None:
            raise CommandError("no_such_run", f"no finished run {run_id!r} in {config.runs_dir}")
        return record

    runtime.control.register("run", run)
    runtime.details = core.status
    for run_id in core.recover():
        log.warning("run %s was left by a controller that died; finished as failed from its journal", run_id)

    def on_motion() -> None:
        estimate = motion.receive(timeout_s=0)
        if estimate is None:
            return
        core.on_estimate(estimate)
        runtime.state = "running" if core.state == "servoing" else "idle"

    runtime.add_reader(motion.socket, on_motion)

    def step() -> float:
        wait = core.tick()
        runtime.state = "running" if core.state == "servoing" else "idle"
        return wait

    try:
        return runtime.run(step)
    finally:
        if core.state == "servoing":
            # Bounded: a launcher stopping everything gives each service a few seconds,
            # and a peer that is already gone must not use them all up.
            for client in (stage_client, estimator_client):
                client.timeout_s, client.retries, client.cancelled = 0.3, 1, None
            core.stop("controller shutting down")
        events.close()
        motion.close()
        runtime.context.destroy(linger=0)  # closes what is still open: term() would wait on it


if __name__ == "__main__":
    raise SystemExit(main())
