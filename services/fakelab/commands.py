"""The fake lab's command handlers (declared in :mod:`semservo.protocol.fakelab`):
functions of a :class:`FakeLab` and a checked request, testable without a socket."""

from __future__ import annotations

import logging
import threading
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np

from semservo.errors import BadRequest
from semservo.protocol import Handlers, NoArguments, OpenReply
from semservo.protocol import fakelab as protocol
from semservo.simulation.world import PRESETS, World

log = logging.getLogger("fakelab")


@dataclass
class FakeLab:
    """What the handlers work on: the world, the serial cable, and where things are."""

    world: World
    plugged: threading.Event
    describe_links: Callable[[], dict]  # serial pty path, TCP URL, scan endpoint

    def describe(self) -> dict:
        return {**self.world.describe(), **self.describe_links()}


handlers: Handlers[FakeLab] = Handlers(protocol.COMMANDS)


@handlers.handles(protocol.INFO)
def info(lab: FakeLab, _request: NoArguments) -> OpenReply:
    return OpenReply.model_validate(lab.describe())


def _simulated_time(lab: FakeLab, value: float, name: str) -> float:
    """A past simulated time: from 0 to now."""
    now = lab.world.now()
    if value > now:
        raise BadRequest(f"{name} {value!r} is in the future (now {now:.3f} s)")
    return value


@handlers.handles(protocol.POSE)
def pose(lab: FakeLab, request: protocol.PoseRequest) -> protocol.Pose:
    """The true pose now, or at a past simulated time ``t_s`` (e.g. when a frame was
    scanned: frame labels carry it), or averaged over a scan ``interval_s`` (t0, t1):
    what a frame shows, with the vibration averaged out as the scan averages it."""
    world = lab.world
    if request.interval_s is not None:
        start, end = (_simulated_time(lab, value, "interval_s") for value in request.interval_s)
        if start < 0:
            raise BadRequest(f"interval_s must be past simulated times, 0..{world.now():.3f} s")
        if start > end:
            raise BadRequest(f"interval_s must be ordered, got {start:g} > {end:g}")
        samples = [asdict(world.pose(t)) for t in np.linspace(start, end, 64)]
        return protocol.Pose.model_validate({"interval_s": [start, end], "world_id": world.id,
                                             **{key: float(np.mean([sample[key] for sample in samples]))
                                                for key in samples[0]}})
    when = _simulated_time(lab, request.t_s, "t_s") if request.t_s is not None else world.now()
    return protocol.Pose.model_validate({"t_s": when, "world_id": world.id, **asdict(world.pose(when)),
                                         "voltages": [world.voltage(channel) for channel in (0, 1, 2)]})


@handlers.handles(protocol.SET_ROTATION_STAGE)
def set_rotation_stage(lab: FakeLab, request: protocol.RotationStageRequest) -> OpenReply:
    """Send the rotation-and-tilt stage towards these angles (it moves at its own
    speed), or halt it; always says where it is, where it is going and when it gets
    there."""
    world = lab.world
    angles = request.model_dump(exclude_none=True, exclude={"halt"})
    try:
        if request.halt:
            world.halt_rotation_stage()
        world.set_rotation_stage(**angles)
    except (TypeError, ValueError) as error:
        raise BadRequest(str(error)) from None
    return OpenReply.model_validate({**world.rotation_stage, "targets_deg": world.goniometer.targets(),
                                     "settles_in_s": world.rotation_stage_settles_in_s()})


@handlers.handles(protocol.SET_PRESET)
def set_preset(lab: FakeLab, request: protocol.PresetRequest) -> OpenReply:
    if request.preset not in PRESETS:
        raise BadRequest(f"preset must be one of {', '.join(sorted(PRESETS))}")
    lab.world.set_preset(PRESETS[request.preset])  # not while a frame renders with the old SEM; a sample image stays
    return OpenReply.model_validate(lab.describe())


@handlers.handles(protocol.SERIAL_LINK)
def serial_link(lab: FakeLab, request: protocol.SerialLinkRequest) -> protocol.SerialLink:
    """Pull (``plugged: false``) or plug back the serial cable."""
    if request.plugged is not None:
        (lab.plugged.set if request.plugged else lab.plugged.clear)()
        log.warning("serial cable %s", "plugged in" if request.plugged else "PULLED")
    return protocol.SerialLink(plugged=lab.plugged.is_set())
