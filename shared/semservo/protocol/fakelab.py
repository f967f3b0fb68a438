"""The fake lab's commands (``services/fakelab``): the simulated world's control socket.
A real instrument has none of these; the truth (``pose``) is what lets tests and
benchmarks say how close a run really came.
"""

from __future__ import annotations

from pydantic import Field

from semservo.protocol import CommandReply, CommandRequest, CommandSet, NoArguments, OpenReply

COMMANDS = CommandSet("fakelab", "The simulated lab: a simulated SEM (scans on REP `:5591`), an emulated NV 40/3 "
                                 "(serial protocol on a pseudo-terminal and TCP `:5592`), a rotation-and-tilt stage, "
                                 "one world. REP `:5590`.")


class PoseRequest(CommandRequest):
    """The true pose now, at a past simulated time, or averaged over a scan."""

    t_s: float | None = Field(None, ge=0, description="a past simulated time (s), e.g. a frame's scan time")
    interval_s: list[float] | None = Field(None, min_length=2, max_length=2,
                                           description="[t0, t1] simulated seconds: the pose averaged over a scan")


class Pose(CommandReply):
    model_config = {"extra": "allow"}  # every axis of the world's pose

    world_id: str = Field(description="new at every start: truths across a restart are refused")
    t_s: float | None = None
    interval_s: list[float] | None = None
    x_um: float
    y_um: float
    voltages: list[float] | None = None


class RotationStageRequest(CommandRequest):
    rotation_deg: float | None = Field(None, ge=-360, le=360)
    tilt_x_deg: float | None = Field(None, ge=-45, le=45)
    tilt_y_deg: float | None = Field(None, ge=-45, le=45)
    halt: bool = False


class PresetRequest(CommandRequest):
    preset: str = Field(min_length=1, max_length=64)


class SerialLinkRequest(CommandRequest):
    plugged: bool | None = Field(None, description="pull (false) or plug back (true) the serial cable")


class SerialLink(CommandReply):
    plugged: bool


INFO = COMMANDS.add("info", NoArguments, OpenReply, "preset, world_id, sample_image (a real picture as the sample: its "
                    "name, pixel size and its source, size, edges, noise as read and as used, magnifications allowed; "
                    "null without one), serial pty path and TCP URL, scan endpoint")
POSE = COMMANDS.add("pose", PoseRequest, Pose, "the true pose now, at a past simulated time, or averaged over a "
                                               "scan's interval; with the channel voltages")
SET_ROTATION_STAGE = COMMANDS.add("set_rotation_stage", RotationStageRequest, OpenReply,
                                  "send the rotation-and-tilt stage towards these angles at its own speed, or halt "
                                  "it; says where it is, where it goes and when it gets there (settles_in_s)")
SET_PRESET = COMMANDS.add("set_preset", PresetRequest, OpenReply,
                          "switch the experimental condition (a sample image stays the sample)")
SERIAL_LINK = COMMANDS.add("serial_link", SerialLinkRequest, SerialLink, "pull or plug back the serial cable")
