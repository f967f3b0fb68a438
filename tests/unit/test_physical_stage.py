"""The stage service on a motion driver in physical units (micrometres and degrees): the
same rules as on the NV 40/3 (travel and step per axis, the owner, stop and watchdog,
finite numbers, read-back, the command log), through the service's own handlers."""

from __future__ import annotations

import math
import uuid

import pytest

from semservo.errors import BadRequest, CommandError
from semservo.instruments import PHYSICAL, VOLTAGE, Axis, driver_kind
from semservo.nv40_driver import NV403Driver
from semservo.protocol import LocalPort
from semservo.protocol import stage as protocol
from semservo.simulation.amplifier import SimulatedAmplifier
from semservo.simulation.positioner import SimulatedPositioner
from services.stage.commands import handlers
from services.stage.core import driver_class
from services.stage.physical import PhysicalLimits, PhysicalStageCore


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def make_core(tmp_path=None, **limits) -> tuple[PhysicalStageCore, str, Clock]:
    url = f"sim://{uuid.uuid4().hex}"
    clock = Clock()
    core = PhysicalStageCore(url, open_driver=SimulatedPositioner.open, clock=clock, state_dir=tmp_path,
                             physical=PhysicalLimits(**limits))
    assert core.connect()
    return core, url, clock


def test_the_kind_of_a_driver_picks_the_core():
    assert driver_kind(SimulatedPositioner) == PHYSICAL and driver_kind(driver_class("simulated-positioner")) == PHYSICAL
    assert driver_kind(SimulatedAmplifier) == VOLTAGE and driver_kind(NV403Driver) == VOLTAGE
    with pytest.raises(ValueError, match="needs its motion driver"):
        PhysicalStageCore("sim://nothing")
    core = PhysicalStageCore("sim://amp", open_driver=SimulatedAmplifier.open)
    assert not core.connect() and "not a motion driver" in core.last_error


def test_moves_in_micrometres_on_stage_and_beam_axes_through_the_handlers():
    core, url, _ = make_core()
    stage = LocalPort(handlers, core)
    state = stage.call(protocol.STATE)
    assert state.kind == "physical" and state.voltages == {} and state.link == "connected"
    assert state.axes["beam_x"].moves == "beam" and state.axes["beam_x"].travel == [-5.0, 5.0]
    assert state.axes["x"].max_step == 10.0
    reply = stage.call(protocol.MOVE, targets={"x": 2.5, "beam_y": -0.75}, relative=True)
    assert reply.positions_um == {"x": 2.5, "y": 0.0, "beam_x": 0.0, "beam_y": -0.75}
    assert reply.settled_at_ns >= reply.written_at_ns
    reply = stage.call(protocol.MOVE, targets={"x": 1.0})  # absolute
    assert reply.positions_um["x"] == 1.0 and SimulatedPositioner.devices[url].positions["x"] == 1.0
    assert any("move x-1.5000" in entry.text for entry in stage.call(protocol.LOG).entries)


def test_travel_step_and_non_finite_numbers_are_refused_whole():
    core, url, _ = make_core(max_steps={"beam_x": 1.0}, travel={"x": (-20.0, 20.0)})
    for targets, code in (({"x": 25.0}, "travel_limit"),  # the lab's travel, within the device's 50
                          ({"beam_x": 6.0}, "travel_limit"),  # the beam shift's own
                          ({"x": 12.0, "y": 1.0}, "step_limit"), ({"beam_x": 1.5}, "step_limit"),
                          ({"x": math.nan}, "travel_limit"), ({"y": math.inf}, "travel_limit"),
                          ({"voltage": 1.0}, "bad_axis")):
        with pytest.raises(CommandError) as refused:
            core.move(targets, relative=True)
        assert refused.value.code == code, targets
    assert SimulatedPositioner.devices[url].moves == 0 and core.counters["refused"] == 7
    stage = LocalPort(handlers, core)  # the wire refuses NaN before the core sees it
    with pytest.raises(BadRequest):
        stage.call(protocol.MOVE, targets={"x": math.nan})
    with pytest.raises(CommandError) as refused:
        stage.call(protocol.SET_VOLTAGES, voltages={"x": 1.0})
    assert refused.value.code == "no_voltages"


def test_the_owner_rule_the_stop_and_the_watchdog_hold(tmp_path):
    core, url, clock = make_core(tmp_path)
    core.arm(1.0, "run-a")
    with pytest.raises(CommandError) as refused:
        core.move({"x": 1.0}, relative=True, owner="gateway")
    assert refused.value.code == "owned"
    core.move({"x": 1.0}, relative=True, owner="run-a")
    clock.t = 2.0  # the run's controller goes silent
    core.poll()
    assert core.state == "held" and "holding at x 1.0000 um" in core.state_reason
    with pytest.raises(CommandError) as refused:
        core.move({"x": 1.0}, relative=True, owner="run-a")
    assert refused.value.code == "held"
    core.resume()
    core.stop("operator")
    assert SimulatedPositioner.devices[url].halts == 2  # the watchdog's hold and the stop both halt motion
    with pytest.raises(CommandError) as refused:
        core.move({"x": 1.0}, relative=True)
    assert refused.value.code == "stopped"
    # A restarted service comes back stopped, with its command log.
    again = PhysicalStageCore(url, open_driver=SimulatedPositioner.open, state_dir=tmp_path)
    assert again.state == "stopped" and any("move x+1.0000" in entry["text"] for entry in again.command_log())


def test_what_the_device_refuses_comes_back_in_its_words_and_a_clip_is_not_applied():
    class Optimistic(SimulatedPositioner):  # documents more travel than it then accepts
        def axes(self):
            return {**super().axes(), "x": Axis("um", "stage", (-100.0, 100.0))}

    core = PhysicalStageCore(f"sim://{uuid.uuid4().hex}", open_driver=Optimistic.open,
                             physical=PhysicalLimits(max_step_um=50.0))
    core.connect()
    core.move({"x": 45.0})
    with pytest.raises(CommandError) as refused:
        core.move({"x": 8.0}, relative=True)
    assert refused.value.code == "device_refused" and "x: 53.0000 um is out of range [-50, 50]" in refused.value.message

    class Clipping(SimulatedPositioner):  # a device that clips in silence, as an SDK's beam shift may
        def move_by(self, steps):
            return super().move_by({axis: max(min(step, 0.5), -0.5) for axis, step in steps.items()})

    clipped = PhysicalStageCore(f"sim://{uuid.uuid4().hex}", open_driver=Clipping.open)
    clipped.connect()
    with pytest.raises(CommandError) as refused:
        clipped.move({"beam_x": 2.0}, relative=True)
    assert refused.value.code == "not_applied" and "beam_x at 0.5000 um, sent to 2.0000" in refused.value.message


def test_an_axis_moved_by_someone_else_stops_the_stage_and_a_pulled_cable_is_link_lost():
    core, url, clock = make_core()
    device = SimulatedPositioner.devices[url]
    device.positions["y"] += 3.0  # the microscope's own software moves the stage
    clock.t = 5.0
    core.poll()
    assert core.state == "stopped" and "y 0.0000 -> 3.0000 um" in core.state_reason
    assert core.describe()["positions_um"]["y"] == 3.0
    core.resume()
    device.plugged = False
    clock.t = 10.0
    core.poll()
    assert core.link == "lost"
    with pytest.raises(CommandError) as refused:
        core.move({"x": 1.0}, relative=True)
    assert refused.value.code == "link_lost"
    device.plugged = True
    clock.t = 20.0
    core.poll()
    assert core.link == "connected" and core.counters["reconnects"] == 1


def test_degree_axes_turn_through_rotate_and_an_axis_without_travel_is_refused_at_connect():
    class Goniometer(SimulatedPositioner):
        def axes(self):
            return {**super().axes(), "rotation_deg": Axis("deg", "stage", (-180.0, 180.0)),
                    "tilt_x_deg": Axis("deg", "stage")}

        def read_positions(self):
            return {"rotation_deg": 0.0, "tilt_x_deg": 0.0, **super().read_positions()}

        def move_by(self, steps):
            self.device.positions.update({axis: self.read_positions()[axis] + step for axis, step in steps.items()})
            return self.read_positions()

    core = PhysicalStageCore(f"sim://{uuid.uuid4().hex}", open_driver=Goniometer.open)
    assert not core.connect() and "tilt_x_deg' has no finite travel" in core.last_error
    core = PhysicalStageCore(f"sim://{uuid.uuid4().hex}", open_driver=Goniometer.open,
                             physical=PhysicalLimits(travel={"tilt_x_deg": (-10.0, 10.0)}))
    assert core.connect()
    turned = LocalPort(handlers, core).call(protocol.ROTATE, targets={"rotation_deg": 12.0}, relative=True)
    assert turned.angles_deg["rotation_deg"] == 12.0
    with pytest.raises(CommandError) as refused:
        core.rotate({"tilt_x_deg": 11.0})
    assert refused.value.code == "rotation_limit"
    with pytest.raises(CommandError) as refused:
        core.rotate({"rotation_deg": 45.0}, relative=True)
    assert refused.value.code == "step_limit"
    state = LocalPort(handlers, core).call(protocol.STATE)
    assert state.rotation.travel_deg == {"rotation_deg": [-180.0, 180.0], "tilt_x_deg": [-10.0, 10.0]}


def test_the_stage_settings_make_the_physical_core(monkeypatch, tmp_path):
    from semservo.config import Settings
    from services.stage.core import StageLimits
    from services.stage.physical import physical_core

    monkeypatch.setenv("SEMSERVO_STAGE__TRAVEL", '{"x": [-40, 40]}')
    monkeypatch.setenv("SEMSERVO_STAGE__MAX_STEPS", '{"beam_x": 1}')
    monkeypatch.setenv("SEMSERVO_STAGE__MAX_STEP_UM", "2")
    monkeypatch.setenv("SEMSERVO_STAGE__STATE_DIR", str(tmp_path))
    core = physical_core(f"sim://{uuid.uuid4().hex}", SimulatedPositioner, Settings().stage, StageLimits())
    assert core.connect()
    axes = core.describe()["axes"]
    assert axes["x"]["travel"] == [-40.0, 40.0] and axes["y"]["travel"] == [-50.0, 50.0]  # the lab's, the device's
    assert (axes["x"]["max_step"], axes["beam_x"]["max_step"], axes["beam_y"]["max_step"]) == (2.0, 1.0, 2.0)
