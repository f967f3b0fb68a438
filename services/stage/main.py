"""Stage process: a stage driver (the NV 40/3 on its serial link by default) behind a
request-reply socket. The commands are declared in :mod:`semservo.protocol.stage` and
answered by :mod:`services.stage.commands`; every rule is the core's
(:mod:`services.stage.core`).

Run it with ``semservo service stage``; settings ``SEMSERVO_STAGE__*``.
"""

from __future__ import annotations

import argparse
import logging

from semservo.config import Settings, connect
from semservo.logs import configure
from semservo.service import ServiceRuntime
from semservo.transport import ControlClient
from services.stage.commands import handlers
from semservo.instruments import PHYSICAL, driver_kind
from services.stage.core import StageCore, StageLimits, driver_class, models_from
from services.stage.physical import physical_core
from services.stage.rotation import FakelabRotationStage

log = logging.getLogger("stage")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="semservo service stage",
        description="Own the NV 40/3's serial link: moves through the displacement-voltage model, "
                    "soft limits, step and rate limits, a watchdog and a stop that always works.",
    )
    parser.add_argument("--url", help="the driver's link: pyserial URL of the amplifier (default: settings, the fake "
                                      "lab's TCP port), openfibsem://MANUFACTURER@HOST for openfibsem")
    parser.add_argument("--driver", help="stage driver: nv40 (default), simulated, openfibsem, simulated-positioner, "
                                         "an entry point or package.module:ClassName")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    settings = Settings()
    configure(settings.log_level)
    config = settings.stage
    runtime = ServiceRuntime("stage", settings, settings.bind(config.control_port))
    limits = StageLimits(config.voltage_min, config.voltage_max, config.travel_min_um, config.travel_max_um,
                         config.max_step_v, config.max_rate_v_per_s, config.max_turn_deg)
    rotation = None
    if config.rotation_stage == "fakelab":
        # Short timeouts: a turn must not stall the service that also has to stop at once.
        rotation = FakelabRotationStage(ControlClient(connect(settings.fakelab.host, settings.fakelab.control_port),
                                                      timeout_s=min(settings.request_timeout_s, 1.0), retries=1,
                                                      context=runtime.context))
    driver = driver_class(args.driver or config.driver)
    if driver_kind(driver) == PHYSICAL:  # micrometres and degrees: a closed-loop stage, a microscope's stage and beam
        core = physical_core(args.url or config.serial_url, driver, config, limits, rotation)
    else:
        core = StageCore(args.url or config.serial_url, limits=limits, channels=dict(config.axes),
                         models=models_from(config.model_files, config.axes), state_dir=config.state_dir,
                         open_driver=driver.open, rotation=rotation, settle_s=dict(config.settle_s))
    core.connect()

    handlers.bind(runtime.control, core)
    runtime.report_errors_from(lambda: core.last_error)

    runtime.details = core.describe

    def step() -> float:
        wait = core.poll()
        runtime.state = "running" if core.link == "connected" else "degraded"
        return wait

    try:
        return runtime.run(step)
    finally:
        core.shutdown()
        runtime.context.destroy(linger=0)  # closes what is still open: term() would wait on it


if __name__ == "__main__":
    raise SystemExit(main())
