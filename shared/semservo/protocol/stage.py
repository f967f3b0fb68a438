"""The stage service's commands (``services/stage``): every axis moves through these.

A refused command is a :class:`~semservo.errors.CommandError` whose code names the rule:
``travel_limit``, ``voltage_limit``, ``step_limit``, ``rate_limit``, ``held``, ``stopped``,
``link_lost``, ``not_applied``, ``bad_axis``, ``owned`` (a run's controller has the
stage armed), ``model_jump`` (the displacement model asks for far more voltage than the
move can need), ``rotation_limit``, ``no_rotation_stage``, ``rotation_link_lost``,
``device_refused`` (the device's own refusal, in its words), ``no_voltages`` (a motion
driver in physical units has no voltages to set).

Two kinds of driver sit behind the same commands (``state``'s ``kind``): ``voltage``, an
amplifier's channels through each axis's displacement-voltage model (the NV 40/3), and
``physical``, axes that take micrometres and degrees themselves and report where they
are (a closed-loop stage, a microscope's stage and beam shift through OpenFIBSEM:
``state``'s ``axes``).
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from semservo.protocol import CommandReply, CommandRequest, CommandSet, NoArguments

COMMANDS = CommandSet("stage", "Owns every axis: the piezo amplifier (NV 40/3 on RS-232 by default, or any "
                               "`StageDriver`) or axes in micrometres and degrees (a `MotionDriver`: a closed-loop "
                               "stage, a microscope's stage and beam shift through OpenFIBSEM), the rotation-and-tilt "
                               "stage, their limits, the watchdog and the stop. REP `:5570`.")

#: An axis name (``x``, ``y``; ``rotation_deg``, ``tilt_x_deg``, ``tilt_y_deg`` for turns).
AxisName = Annotated[str, Field(min_length=1, max_length=32)]
#: Who asks: a run's controller names itself; a jog is ``gateway``.
Owner = Annotated[str, Field(min_length=1, max_length=100)]


class MoveRequest(CommandRequest):
    targets: dict[AxisName, float] = Field(min_length=1, max_length=8, description="axis -> um: where to, or by how "
                                                                                   "much when relative (x, y; a "
                                                                                   "beam shift: beam_x, beam_y)")
    relative: bool = False
    owner: Owner | None = None


class MoveReply(CommandReply):
    written_at_ns: int = Field(description="Unix ns the set points were written")
    voltages: dict[str, float] = Field(description="every axis's output as read back")
    positions_um: dict[str, float] = Field(description="every axis's position as its model estimates it")
    settled_at_ns: int | None = Field(None, description="Unix ns the stage will have settled (from each axis's "
                                                        "settling time); frames scanned before show it moving")
    ready_at_ns: int | None = Field(None, description="Unix ns from which any step the step limit allows is within "
                                                      "the rate limit (a chained move's next command waits for it and "
                                                      "for settled_at_ns)")


class RotateRequest(CommandRequest):
    targets: dict[AxisName, float] = Field(min_length=1, max_length=3, description="rotation_deg, tilt_x_deg, "
                                                                                   "tilt_y_deg: degrees")
    relative: bool = False
    owner: Owner | None = None


class RotateReply(CommandReply):
    written_at_ns: int
    angles_deg: dict[str, float] = Field(description="where every axis is now (a turn takes time)")
    targets_deg: dict[str, float] = Field(description="where they are going")
    settled_at_ns: int = Field(description="Unix ns the turn will have arrived: frames scanned before are stale")


class SetVoltagesRequest(CommandRequest):
    voltages: dict[AxisName, float] = Field(min_length=1, max_length=8, description="axis -> volts (calibration)")
    owner: Owner | None = None


class ArmRequest(CommandRequest):
    hold_after_s: float = Field(ge=0.05, le=600, description="hold if the owner is silent this long (watchdog)")
    owner: Owner


class OwnerRequest(CommandRequest):
    owner: Owner | None = None


class StopRequest(CommandRequest):
    reason: str = Field("stop requested", max_length=500)


class LogRequest(CommandRequest):
    since_ns: int = Field(0, ge=0, le=2**63 - 1, description="Unix ns")


class LogEntry(CommandReply):
    time_ns: int
    direction: Literal["sent", "received"] | str
    text: str


class LogReply(CommandReply):
    entries: list[LogEntry]


#: Who stopped the stage: a stop command ("request": an operator, the gateway, a script) or
#: the stage service's own checks ("stage": outputs it did not command, a release).
StoppedBy = Literal["request", "stage"]


class HeartbeatReply(CommandReply):
    state: Literal["ready", "stopped", "held"]
    reason: str
    stopped_by: StoppedBy | None = Field(None, description="when stopped: by a stop command or by the stage itself")
    watchdog: bool
    owner: str | None


class Watchdog(CommandReply):
    armed: bool
    timeout_s: float
    owner: str | None


class Limits(CommandReply):
    voltage_min: float
    voltage_max: float
    travel_min_um: float
    travel_max_um: float
    max_step_v: float
    max_rate_v_per_s: float
    max_turn_deg: float
    device_voltage: list[float]


class RotationStage(CommandReply):
    angles_deg: dict[str, float] | None = Field(description="as last read (null before the first read)")
    travel_deg: dict[str, list[float]]
    link: str


class AxisState(CommandReply):
    """One axis of a motion driver in physical units (``kind`` ``physical``)."""

    unit: Literal["um", "deg"]
    moves: Literal["stage", "beam"] = Field(description="the stage (the sample) or the beam (a beam shift)")
    position: float | None = Field(description="as last read back, in the device's coordinates")
    travel: list[float] = Field(description="[min, max]: the device's own, narrowed by the lab's")
    max_step: float = Field(description="the largest displacement one command may ask")


class StageState(CommandReply):
    """What the stage service says of itself (``state``, and every other command's
    context: ``GET /stage``)."""

    url: str = Field(description="the driver's link (serial URL)")
    link: Literal["connecting", "connected", "lost"]
    state: Literal["ready", "stopped", "held"]
    reason: str
    stopped_by: StoppedBy | None = Field(None, description="when stopped: by a stop command (an operator, the "
                                                           "gateway, a script) or by the stage itself")
    device: str | None = Field(description="what the device says it is")
    voltages: dict[str, float]
    positions_um: dict[str, float]
    limits: Limits
    watchdog: Watchdog
    models: dict[str, str] = Field(description="each axis's displacement-voltage model")
    settle_s: dict[str, float] = Field(default_factory=dict, description="each axis's settling time after a move")
    rotation: RotationStage | None = Field(description="the rotation-and-tilt stage; null when the lab has none")
    kind: Literal["voltage", "physical"] = Field("voltage", description="the driver's: voltage (an amplifier's "
                                                                        "channels) or physical (um and degrees)")
    axes: dict[str, AxisState] = Field(default_factory=dict, description="a physical driver's axes (x, y, beam_x, "
                                                                         "beam_y, ...)")
    settled_at_ns: int = Field(0, description="Unix time (ns) the last move, turn or voltage write has settled (0: "
                                             "none since the service started); frames scanned before show a pose "
                                             "in between")
    last_error: str | None
    moves: int
    turns: int
    refused: int
    link_lost: int
    reconnects: int
    uncommanded_changes: int


STATE = COMMANDS.add("state", NoArguments, StageState, "link, state, voltages, positions, limits, watchdog, the "
                                                       "rotation stage as last read")
MOVE = COMMANDS.add("move", MoveRequest, MoveReply, "move axes to or by micrometres (through each axis's "
                                                    "displacement-voltage model on an amplifier); refused whole, "
                                                    "never clipped")
ROTATE = COMMANDS.add("rotate", RotateRequest, RotateReply, "turn or tilt the rotation-and-tilt stage (or a "
                                                            "physical driver's degree axes), relative to where the "
                                                            "last command sent each axis")
SET_VOLTAGES = COMMANDS.add("set_voltages", SetVoltagesRequest, MoveReply, "raw voltages (calibration), under the "
                                                                           "limits of a move")
ARM = COMMANDS.add("arm", ArmRequest, StageState, "a run claims the stage: moves for its owner only, held if it is "
                                                  "silent for hold_after_s")
DISARM = COMMANDS.add("disarm", OwnerRequest, StageState, "the run releases the stage")
HEARTBEAT = COMMANDS.add("heartbeat", OwnerRequest, HeartbeatReply, "feed the watchdog; says the stage's state")
STOP = COMMANDS.add("stop", StopRequest, StageState, "hold at once and refuse moves until resumed (any state, link "
                                                     "up or not)")
RESUME = COMMANDS.add("resume", NoArguments, StageState, "let a stopped or held stage move again")
RELEASE = COMMANDS.add("release", NoArguments, StageState, "give the channels back to the front panel, and stop")
LOG = COMMANDS.add("log", LogRequest, LogReply, "every line exchanged with the amplifier since since_ns (kept "
                                                "across restarts)", timeout_s=5.0)
