"""The stage service's core on a real serial link: the emulated NV 40/3 on a
pseudo-terminal, opened through pyserial; and the controller's core driving it."""

from __future__ import annotations

import pytest

from semservo import nv40
from semservo.messages import MotionEstimate
from semservo.simulation.world import World
from services.controller.core import ControllerCore, RunSettings
from services.fakelab.emulator import ChannelState, NV403Emulator
from services.fakelab.serial_links import PseudoTerminalLink
from services.stage.core import Refused, StageCore, StageLimits

pytestmark = pytest.mark.integration


class FakeClock:
    def __init__(self):
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def link():
    world = World(speedup=100.0)
    channels = {channel: ChannelState(knob_voltage=world.voltage(channel)) for channel in nv40.CHANNELS}
    pty = PseudoTerminalLink(lambda: NV403Emulator(world, channels=channels)).start()
    yield world, pty
    pty.stop()


@pytest.fixture
def stage(link):
    _, pty = link
    clock = FakeClock()
    core = StageCore(pty.path, limits=StageLimits(max_rate_v_per_s=1e6), clock=clock)
    assert core.connect()
    yield core
    core.close()


def test_connects_takes_remote_control_and_moves_through_the_model(stage, link):
    world, _ = link
    assert stage.link == "connected" and stage.device["prompt"] == nv40.PROMPT_CLOSED_LOOP_MODEL
    start = stage.positions()["x"]
    result = stage.move({"x": 2.0}, relative=True)
    assert stage.positions()["x"] == pytest.approx(start + 2.0)
    assert world.voltage(0) == pytest.approx(result["voltages"]["x"], abs=1e-3)
    assert result["voltages"]["x"] > 38.0


def test_refusals_name_the_rule_and_change_nothing(stage):
    before = dict(stage.voltages)
    for call, code in [
        (lambda: stage.move({"x": 101.0}), "travel_limit"),
        (lambda: stage.move({"x": 25.0}, relative=True), "step_limit"),
        (lambda: stage.set_voltages({"x": -19.5}), "voltage_limit"),
        (lambda: stage.move({"z": 1.0}), "bad_axis"),
    ]:
        with pytest.raises(Refused) as refusal:
            call()
        assert refusal.value.code == code
    assert stage.voltages == before


def test_rate_limit(link):
    _, pty = link
    clock = FakeClock()
    core = StageCore(pty.path, limits=StageLimits(max_rate_v_per_s=100.0), clock=clock)
    assert core.connect()
    core.set_voltages({"x": 40.0})
    clock.now += 0.01
    with pytest.raises(Refused) as refusal:
        core.set_voltages({"x": 45.0})  # 5 V in 10 ms = 500 V/s
    assert refusal.value.code == "rate_limit"
    clock.now += 0.1
    core.set_voltages({"x": 45.0})
    core.close()


def test_watchdog_holds_a_silent_controller_and_stop_always_works(stage):
    stage.arm(2.0, owner="controller-a")
    stage.move({"x": 1.0}, relative=True, owner="controller-a")
    stage.clock.now += 1.5
    stage.heartbeat("controller-a")
    stage.clock.now += 1.5
    stage.poll()
    assert stage.state == "ready"
    stage.clock.now += 2.5
    stage.poll()
    assert stage.state == "held" and "silent" in stage.state_reason
    with pytest.raises(Refused, match="held"):
        stage.move({"x": 0.1}, relative=True)
    stage.stop("operator")
    with pytest.raises(Refused) as refusal:
        stage.move({"x": 0.1}, relative=True)
    assert refusal.value.code == "stopped"
    stage.resume()
    stage.move({"x": 0.1}, relative=True)


def test_a_reversal_does_not_jump_between_hysteresis_branches(stage):
    up = stage.move({"x": 3.0}, relative=True)["voltages"]["x"]
    back = stage.move({"x": -0.1}, relative=True)["voltages"]["x"]
    assert 0 < up - back < 0.5  # a 0.1 um correction is a fraction of a volt, not a branch jump


class LocalStage:
    """The controller's port onto an in-process stage core (the service maps the same
    commands onto the same methods)."""

    def __init__(self, core: StageCore):
        self.core = core

    def request(self, command: str, args: dict | None = None) -> dict:
        args = args or {}
        if command == "arm":
            return self.core.arm(args["hold_after_s"], args["owner"])
        if command == "move":
            return self.core.move(args["targets"], relative=args["relative"], owner=args["owner"])
        if command == "log":
            return {"entries": self.core.command_log(args["since_ns"])}
        return getattr(self.core, command)(*args.values())


def estimate(seq: int, dx: float, dy: float, *, confidence: float = 0.9, scan_started_at_ns: int) -> MotionEstimate:
    return MotionEstimate(seq=seq, reference_id="ref", dx_px=dx, dy_px=dy, rotation_deg=0.0, confidence=confidence,
                          snr_db=20.0, filtered=False, pixel_size_nm=177.0, frame_acquired_at_ns=scan_started_at_ns + 1,
                          frame_published_at_ns=scan_started_at_ns + 2, frame_scan_started_at_ns=scan_started_at_ns,
                          frame_source_interval_s=(seq * 0.5, seq * 0.5 + 0.45), published_at_ns=scan_started_at_ns + 3,
                          estimation_ms=1.0, latency_ms=1.0)


def test_controller_acts_only_on_fresh_confident_estimates(stage, tmp_path):
    import time

    core = ControllerCore(LocalStage(stage), runs_dir=tmp_path, watchdog_s=2.0)
    core.start(RunSettings(converge_frames=2, lost_after=3), "ref")
    before = time.time_ns()
    stale = core.on_estimate(estimate(1, 20.0, 0.0, scan_started_at_ns=before - 10**9))
    assert stale["action"].startswith("held: stale")
    moved = core.on_estimate(estimate(2, 20.0, -10.0, scan_started_at_ns=time.time_ns()))
    assert moved["action"] == "moved" and moved["move"]["x_um"] < 0 < moved["move"]["y_um"]
    assert moved["latency_ms"] > 0
    in_flight = core.on_estimate(estimate(3, 15.0, -7.0, scan_started_at_ns=moved["command_written_at_ns"] - 1))
    assert in_flight["action"].startswith("held: stale")
    for seq in (4, 5, 6):
        record = core.on_estimate(estimate(seq, 15.0, -7.0, confidence=0.1, scan_started_at_ns=time.time_ns()))
    assert record["action"] == "held: low confidence"
    assert core.state == "failed" and "scene lost" in core.reason
    assert (tmp_path / f"{core.run['id']}.json").is_file()


def test_controller_converges_and_stop_stops_the_stage(stage, tmp_path):
    import time

    core = ControllerCore(LocalStage(stage), runs_dir=tmp_path)
    core.start(RunSettings(converge_frames=2), "ref")
    core.on_estimate(estimate(1, 0.05, 0.02, scan_started_at_ns=time.time_ns()))
    core.on_estimate(estimate(2, -0.04, 0.03, scan_started_at_ns=time.time_ns()))
    assert core.state == "converged"
    core.start(RunSettings(), "ref")
    core.stop("operator pressed stop")
    assert core.state == "stopped" and stage.state == "stopped"


def test_converging_on_each_frame_asks_every_one_to_be_within(stage, tmp_path):
    import time

    def feed(core, errors):
        for seq, dx in enumerate(errors, 1):
            core.on_estimate(estimate(seq, dx, 0.0, scan_started_at_ns=time.time_ns()))
        return core.state

    # Mean of (0.15, -0.04) is 0.055 px: under 0.1 px on the mean, not on each frame.
    on_mean = ControllerCore(LocalStage(stage), runs_dir=tmp_path)
    on_mean.start(RunSettings(converge_frames=2), "ref")
    assert feed(on_mean, [0.15, -0.04]) == "converged"
    on_each = ControllerCore(LocalStage(stage), runs_dir=tmp_path)
    on_each.start(RunSettings(converge_frames=2, converge_on="each"), "ref")
    assert feed(on_each, [0.15, -0.04]) == "servoing"
    assert on_each.on_estimate(estimate(3, -0.03, 0.0, scan_started_at_ns=time.time_ns()))["action"] == "within tolerance"
    assert on_each.state == "converged"
