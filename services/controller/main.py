"""Controller process: motion (SUB, from the estimator) -> core -> stage service (REQ).

The commands are declared in :mod:`semservo.protocol.controller` and answered by
:mod:`services.controller.commands`. At start it finishes the runs a killed controller
left (``ControllerCore.recover``). Events on the status PUB socket (topic
``controller``): ``status`` and ``iteration``.

Run it with ``semservo service controller``; settings ``SEMSERVO_CONTROLLER__*``.
"""

from __future__ import annotations

import argparse
import logging

from semservo.config import Settings, connect
from semservo.logs import configure
from semservo.messages import CONTROLLER_TOPIC, MOTION_TOPIC, ControllerEvent, MotionEstimate
from semservo.protocol import ServicePort
from semservo.service import ServiceRuntime
from semservo.transport import ControlClient, MessagePublisher, MessageSubscriber
from services.controller.commands import Controller, handlers
from services.controller.core import ControllerCore

log = logging.getLogger("controller")


def build_parser() -> argparse.ArgumentParser:
    return argparse.ArgumentParser(
        prog="semservo service controller",
        description="Drive the stage until the current image matches the taught one (paper eq. 30-37).",
    )


def estimator_ports(client: ControlClient) -> tuple[ServicePort, ServicePort]:
    """The controller's two ports onto the estimator's control socket (one client): the
    running loop's, whose commands give up after the client's tries (1 s each) but for
    those that declare longer (``report``, :mod:`semservo.protocol.estimator`), and a run
    start's, more patient with ``measure`` too.

    Right after a teach (its transforms planned, its focus sweeps' planes fitted in
    another thread), with a benchmark on the other core, the estimator answered a start's
    ``measure`` past 2 tries of 1 s: the run was refused for nothing. Two tries of 4 s
    keep a start within the gateway's 15 s for it; the loop and a run's end (when the
    estimator may be dead) keep their 1 s.
    """
    return ServicePort(client), ServicePort(client, timeouts={"measure": 4.0})


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
        events.publish(ControllerEvent(kind=kind, run_id=core.run and core.run.id, data=data))

    estimator, estimator_at_start = estimator_ports(estimator_client)
    core = ControllerCore(ServicePort(stage_client), estimator=estimator, camera=config.camera_to_stage(),
                          runs_dir=config.runs_dir, watchdog_s=config.watchdog_s, publish=publish,
                          estimator_at_start=estimator_at_start)
    motion = MessageSubscriber(connect(settings.estimator.host, settings.estimator.motion_port), MOTION_TOPIC,
                               MotionEstimate, context=runtime.context, counters=runtime.counters)
    runtime.report_errors_from(lambda: motion.last_error)

    handlers.bind(runtime.control, Controller(core, estimator, config.runs_dir))
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
                client.max_timeout_s, client.retries, client.cancelled = 0.3, 1, None
            core.stop("controller shutting down")
        events.close()
        motion.close()
        runtime.context.destroy(linger=0)  # closes what is still open: term() would wait on it


if __name__ == "__main__":
    raise SystemExit(main())
