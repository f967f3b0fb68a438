"""Stage process: a stage driver (the NV 40/3 on its serial link by default) behind a
request-reply socket.

Commands (``semservo.transport.ControlClient``): ``state``, ``move`` {targets: {axis:
um}, relative, owner}, ``rotate`` {targets: {rotation_deg | tilt_x_deg | tilt_y_deg:
degrees}, relative, owner} (the rotation-and-tilt stage), ``set_voltages`` {voltages: {axis: V}, owner}, ``arm`` {hold_after_s,
owner}, ``disarm``, ``heartbeat`` {owner}, ``stop`` {reason}, ``resume``, ``release``,
``log`` {since_ns}, and ``health``. A refused command answers an error whose code names
the rule (``travel_limit``, ``voltage_limit``, ``step_limit``, ``rate_limit``, ``held``,
``stopped``, ``link_lost``, ``owned``, ``rotation_limit``, ``no_rotation_stage``,
``rotation_link_lost``, ...).

Run it with ``semservo service stage``; settings ``SEMSERVO_STAGE__*``.
"""

from __future__ import annotations

import argparse
import logging

from semservo.config import Settings, connect
from semservo.logs import configure
from semservo.service import ServiceRuntime
from semservo.transport import BadRequest, CommandError, ControlClient, number
from services.stage.core import Refused, StageCore, StageLimits, driver_class, models_from
from services.stage.rotation import FakelabRotationStage

log = logging.getLogger("stage")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="semservo service stage",
        description="Own the NV 40/3's serial link: moves through the displacement-voltage model, "
                    "soft limits, step and rate limits, a watchdog and a stop that always works.",
    )
    parser.add_argument("--url", help="pyserial URL of the amplifier (default: settings, the fake lab's TCP port)")
    parser.add_argument("--driver", help="stage driver: nv40 (default), simulated, an entry point or "
                                         "package.module:ClassName")
    return parser


def _numbers(mapping, name: str) -> dict[str, float]:
    if not isinstance(mapping, dict) or not mapping:
        raise BadRequest(f"{name} must be an object of axis -> number")
    out = {}
    for axis, value in mapping.items():
        out[str(axis)] = number(value, f"{name}.{axis}")
    return out


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
    core = StageCore(args.url or config.serial_url, limits=limits, channels=dict(config.axes),
                     models=models_from(config.model_files, config.axes), state_dir=config.state_dir,
                     open_driver=driver_class(args.driver or config.driver).open, rotation=rotation)
    core.connect()

    def guarded(action):
        def handler(request_args: dict) -> dict:
            try:
                return action(request_args)
            except Refused as refusal:
                raise CommandError(refusal.code, str(refusal)) from None
        return handler

    def owner(request_args: dict) -> str | None:
        value = request_args.get("owner")
        return None if value is None else str(value)

    def move(request_args: dict) -> dict:
        relative = request_args.get("relative", False)
        if not isinstance(relative, bool):
            raise BadRequest("relative must be true or false")
        return core.move(_numbers(request_args.get("targets"), "targets"), relative=relative, owner=owner(request_args))

    def rotate(request_args: dict) -> dict:
        relative = request_args.get("relative", False)
        if not isinstance(relative, bool):
            raise BadRequest("relative must be true or false")
        return core.rotate(_numbers(request_args.get("targets"), "targets"), relative=relative,
                           owner=owner(request_args))

    def arm(request_args: dict) -> dict:
        timeout = number(request_args.get("hold_after_s"), "hold_after_s", "seconds")
        if owner(request_args) is None:
            raise BadRequest("owner is required: the watchdog listens to one controller")
        return core.arm(timeout, owner(request_args))

    def since(request_args: dict) -> dict:
        value = request_args.get("since_ns", 0)
        if isinstance(value, bool) or not isinstance(value, int):
            raise BadRequest("since_ns must be an integer (Unix ns)")
        return {"entries": core.command_log(value)}

    commands = {
        "state": lambda _a: core.describe(),
        "move": move,
        "rotate": rotate,
        "set_voltages": lambda a: core.set_voltages(_numbers(a.get("voltages"), "voltages"), owner=owner(a)),
        "arm": arm,
        "disarm": lambda a: core.disarm(owner(a)),
        "heartbeat": lambda a: core.heartbeat(owner(a)),
        "stop": lambda a: core.stop(str(a.get("reason", "stop requested"))),
        "resume": lambda _a: core.resume(),
        "release": lambda _a: core.release(),
        "log": since,
    }
    for name, action in commands.items():
        runtime.control.register(name, guarded(action))
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
