"""The stage service's core on a real serial link: the emulated NV 40/3 on a
pseudo-terminal, opened through pyserial; and the controller's core driving it."""

from __future__ import annotations

import contextlib
import math
import re
import time

import pytest

from semservo import nv40
from semservo.control import CameraToStage
from semservo.errors import CommandError, ServiceUnavailable
from semservo.messages import MotionEstimate
from semservo.protocol import LocalPort
from semservo.protocol import estimator as estimator_protocol
from semservo.simulation.world import World
from services.controller.core import ControllerCore, RunSettings
from services.stage.commands import handlers as stage_handlers
from services.fakelab.emulator import ChannelState, NV403Emulator
from services.fakelab.serial_links import PseudoTerminalLink
from services.stage.core import Refused, StageCore, StageLimits
from services.stage.rotation import WorldRotationStage

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
    # Settled at once: these tests feed frames scanned right after each move (settling
    # has its own test).
    core = StageCore(pty.path, limits=StageLimits(max_rate_v_per_s=1e6), clock=clock, settle_s={"x": 0.0, "y": 0.0})
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


def test_a_pseudo_terminal_that_goes_away_is_a_lost_link_not_a_crash(link):
    """The emulator killed under a stage on a pseudo-terminal (as a USB adapter pulled
    from /dev/ttyUSB0): tcflush fails with EIO as a termios.error, neither pyserial's
    error nor OSError, and took the stage service down. Now: link_lost, a move refused
    with the reason, polls go on."""
    _, pty = link
    clock = FakeClock()
    core = StageCore(pty.path, limits=StageLimits(max_rate_v_per_s=1e6), clock=clock)
    try:
        assert core.connect()
        pty.stop()  # the device end of the line is gone
        clock.now += 5.0  # past the read-back interval
        for _ in range(3):
            core.poll()
            clock.now += 1.0
        assert core.link == "lost" and core.counters["link_lost"] == 1
        with pytest.raises(Refused) as refusal:
            core.move({"x": 0.5}, relative=True)
        assert refusal.value.code == "link_lost"
    finally:
        core.close()


def test_a_jog_over_the_step_limit_says_the_largest_one_in_micrometres(stage):
    """The request was in um; the refusal says how far one move may go from here (the
    limit itself is in volts), and a move of that size is then taken."""
    with pytest.raises(Refused) as refusal:
        stage.move({"x": 25.0}, relative=True)
    match = re.search(r"one move may take x about ([0-9.]+) um from here", refusal.value.message)
    assert refusal.value.code == "step_limit" and match, refusal.value.message
    largest_um = float(match.group(1))
    assert 5.0 < largest_um < 25.0
    start = stage.positions()["x"]
    stage.move({"x": 0.9 * largest_um}, relative=True)
    assert stage.positions()["x"] == pytest.approx(start + 0.9 * largest_um)


def test_a_model_out_of_step_with_its_axis_is_refused_not_written(stage):
    """However a model came to disagree with its axis, a small move that would need a big
    voltage step is refused with the reason, and nothing reaches the amplifier."""
    before, writes = dict(stage.voltages), sum(1 for entry in stage.driver.log if entry.text.startswith("set"))
    stage.models["x"].offset_v = 9.0  # as the model was before its follow_voltage fix
    with pytest.raises(Refused) as refusal:
        stage.move({"x": -0.03}, relative=True)
    assert refusal.value.code == "model_jump" and "0.030 um move" in refusal.value.message
    assert stage.voltages == before
    assert sum(1 for entry in stage.driver.log if entry.text.startswith("set")) == writes


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


def LocalStage(core: StageCore) -> LocalPort:
    """The controller's port onto an in-process stage core, through the stage service's
    own handlers (the same checks and refusals as over its socket)."""
    return LocalPort(stage_handlers, core)


@contextlib.contextmanager
def connected(pty, **options):
    """A stage core of its own on the emulator's link (``options``: StageCore's), closed after."""
    core = StageCore(pty.path, **options)
    assert core.connect()
    try:
        yield core
    finally:
        core.close()


def as_commanded(content: tuple[float, float], record: dict) -> tuple[float, float]:
    """The content (px at 177 nm/px) after ``record``'s planar move, made exactly as commanded."""
    moved = CameraToStage().content_move_px(record["move"]["x_um"], record["move"]["y_um"], 177.0)
    return content[0] + moved[0], content[1] + moved[1]


def report(reference_id: str | None) -> estimator_protocol.Report:
    reference = None if reference_id is None else estimator_protocol.Reference(
        id=reference_id, kind="frame", shape=[512, 512], pixel_size_nm=177.0, taught_at_ns=1)
    return estimator_protocol.Report(reference=reference, rotation=True, measure_rotation=True, measure_tilts=False,
                                     tilt_reference=None, last_tilt=None, tilt_error=None, precision="full",
                                     latest_frame_seq=None, last_estimate=None)


class FakeEstimator:
    """The estimator's port: what it has taught, and what it was asked to measure."""

    def __init__(self, reference_id: str | None = "ref", latest_frame_seq: int | None = None,
                 estimated_seq: int | None = None):
        self.reference_id = reference_id
        self.latest_frame_seq, self.estimated_seq = latest_frame_seq, estimated_seq
        self.asked = []

    def call(self, command, request=None, /, **fields):
        request = command.build(request, **fields)
        self.asked.append((command.name, request.model_dump()))
        if command is estimator_protocol.REPORT:
            return report(self.reference_id).model_copy(update={
                "latest_frame_seq": self.latest_frame_seq,
                "last_estimate": None if self.estimated_seq is None else {"seq": self.estimated_seq}})
        if command is estimator_protocol.MEASURE:
            return estimator_protocol.MeasureReply(rotation=bool(request.rotation), tilts=bool(request.tilts))
        if command is estimator_protocol.TILTED:
            return estimator_protocol.TiltedReply(restarted=True)
        if command is estimator_protocol.MOVED:
            return estimator_protocol.MovedReply(partial_from_ns=request.settles_at_ns)
        raise AssertionError(f"unexpected {command.name}")


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
    assert (tmp_path / f"{core.run.id}.json").is_file()


def test_a_frame_scanned_while_the_stage_settles_is_stale(link, tmp_path):
    _, pty = link
    with connected(pty, limits=StageLimits(max_rate_v_per_s=1e6), clock=FakeClock(),
                   settle_s={"x": 0.5, "y": 0.2}) as settling:
        core = ControllerCore(LocalStage(settling), runs_dir=tmp_path)
        core.start(RunSettings(), "ref")
        moved = core.on_estimate(estimate(1, 20.0, -10.0, scan_started_at_ns=time.time_ns()))
        assert moved["command_settled_at_ns"] - moved["command_written_at_ns"] == pytest.approx(0.5e9, rel=1e-6)
        during = core.on_estimate(estimate(2, 15.0, -7.0, scan_started_at_ns=moved["command_written_at_ns"] + 10**8))
        assert during["action"].startswith("held: stale")
        settling.clock.now += 1.0  # the rate limit's clock
        # A partial frame of a scan that began during the move: its rows after it settled are fresh.
        scan_began = moved["command_written_at_ns"] + 2 * 10**8
        rows = estimate(3, 15.0, -7.0, scan_started_at_ns=scan_began).model_copy(update={
            "first_row": 288, "rows_scanned_from_ns": moved["command_settled_at_ns"] + 1,
            "rows_source_interval_s": (3 * 0.5 + 0.25, 3 * 0.5 + 0.45)})
        partial = core.on_estimate(rows)
        assert partial["action"] == "moved" and partial["first_row"] == 288
        assert tuple(partial["frame_source_interval_s"]) == (1.75, 1.95), "the record keeps the rows' scan, for the truth"
        settling.clock.now += 1.0
        after = core.on_estimate(estimate(4, 15.0, -7.0, scan_started_at_ns=partial["command_settled_at_ns"] + 1))
        assert not after["action"].startswith("held: stale") and after["first_row"] == 0


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


def test_a_stop_the_stage_does_not_answer_ends_the_run_without_asking_the_stage_again(stage, tmp_path):
    """A controller stopping (Ctrl-C) during a run whose stage service had died: asking
    the dead stage for its log too (a command of 5 s) outlasted the launcher's patience
    and the controller was killed. A stage that missed the stop is asked nothing more."""

    class DyingStage:
        def __init__(self, port):
            self.port, self.dead, self.asked = port, False, []

        def call(self, command, request=None, /, **fields):
            if self.dead:
                self.asked.append(command.name)
                raise ServiceUnavailable("no reply from the stage after 1 tries")
            return self.port.call(command, request, **fields)

    port = DyingStage(LocalStage(stage))
    core = ControllerCore(port, runs_dir=tmp_path)
    core.start(RunSettings(), "ref")
    port.dead = True
    core.stop("controller shutting down")
    assert core.state == "stopped" and port.asked == ["stop"]
    assert "unreachable" in core.run.outcome["stage_log_error"]


def test_a_start_the_stage_refuses_is_named_the_stages_and_the_controllers_own_refusals_keep_their_codes(
        stage, tmp_path):
    core = ControllerCore(LocalStage(stage), runs_dir=tmp_path)
    stage.stop("operator pressed stop")
    with pytest.raises(CommandError) as refused:
        core.start(RunSettings(), "ref")
    assert refused.value.code.startswith("stage_") and "the stage refused to start a run" in refused.value.message
    assert core.state == "idle"
    with pytest.raises(CommandError) as refused:  # the instrument's, said before the stage is asked to arm
        core.start(RunSettings(beam_shift_within_um=1.0), "ref")
    assert refused.value.code == "no_beam_shift"


def test_converging_on_each_frame_asks_every_one_to_be_within(stage, tmp_path):
    import time

    def feed(core, errors):
        for seq, dx in enumerate(errors, 1):
            core.on_estimate(estimate(seq, dx, 0.0, scan_started_at_ns=time.time_ns()))
        return core.state

    # Mean of (0.15, -0.04) is 0.055 px: under 0.1 px on the mean, not on each frame.
    on_mean = ControllerCore(LocalStage(stage), runs_dir=tmp_path)
    # The paper's law's rule (the position law converges on its own estimate).
    on_mean.start(RunSettings(law="paper", converge_frames=2), "ref")
    assert feed(on_mean, [0.15, -0.04]) == "converged"
    on_each = ControllerCore(LocalStage(stage), runs_dir=tmp_path)
    on_each.start(RunSettings(law="paper", converge_frames=2, converge_on="each"), "ref")
    assert feed(on_each, [0.15, -0.04]) == "servoing"
    assert on_each.on_estimate(estimate(3, -0.03, 0.0, scan_started_at_ns=time.time_ns()))["action"] == "within tolerance"
    assert on_each.state == "converged"


def foreign(seq: int, *, scan_started_at_ns: int) -> MotionEstimate:
    return estimate(seq, 1.0, 1.0, scan_started_at_ns=scan_started_at_ns).model_copy(update={"reference_id": "other"})


def test_a_run_fails_at_once_when_its_reference_is_taught_again(stage, tmp_path):
    import time

    core = ControllerCore(LocalStage(stage), runs_dir=tmp_path)
    core.start(RunSettings(), "ref")
    core.on_estimate(foreign(1, scan_started_at_ns=time.time_ns()))  # in flight from before: tolerated
    core.on_estimate(foreign(2, scan_started_at_ns=time.time_ns()))
    assert core.state == "servoing"
    core.on_estimate(foreign(3, scan_started_at_ns=time.time_ns()))
    assert core.state == "failed" and "reference changed" in core.reason and "other" in core.reason


@pytest.mark.parametrize("estimator, says", [(FakeEstimator(None), "no reference (restarted"),
                                             (FakeEstimator("newer"), "now has reference newer"),
                                             (FakeEstimator("ref"), "publishes nothing"),
                                             (FakeEstimator("ref", 41, 40), "publishes nothing"),
                                             (FakeEstimator("ref", 40, 40), "frames stopped: no frame has "
                                                                            "reached the estimator since frame 40")])
def test_a_run_without_estimates_fails_within_the_timeout_saying_why(stage, tmp_path, estimator, says):
    clock = FakeClock()
    core = ControllerCore(LocalStage(stage), estimator=estimator, runs_dir=tmp_path, clock=clock)
    core.start(RunSettings(estimate_timeout_s=5.0), "ref")
    clock.now += 4.9
    core.tick()
    assert core.state == "servoing"
    clock.now += 0.2
    core.tick()
    assert core.state == "failed" and "no estimate against the run's reference for 5.1 s" in core.reason
    assert says in core.reason, core.reason


def test_a_controller_that_did_not_run_for_a_while_blames_no_other_service(stage, tmp_path):
    """Paused (SIGSTOP, a suspended VM) past the estimate deadline, the controller finds
    the estimates' silence its own: the deadline starts again and the stage is asked. An
    operator's stop that reached only the stage meanwhile ends the run as stopped, with
    the operator's reason (it once ended 'failed: frames stopped ... is the image server
    reachable?')."""
    clock = FakeClock()
    core = ControllerCore(LocalStage(stage), estimator=FakeEstimator("ref", 40, 40), runs_dir=tmp_path, clock=clock)
    core.start(RunSettings(estimate_timeout_s=5.0), "ref")
    core.tick()
    clock.now += 6.5  # not run for 6.5 s
    core.tick()
    assert core.state == "servoing", core.reason
    for _ in range(24):  # then ticking as it does, every 0.2 s: 4.8 s
        clock.now += 0.2
        core.tick()
    assert core.state == "servoing", core.reason
    clock.now += 0.3  # the estimates' own silence, counted from the stall's end
    core.tick()
    assert core.state == "failed" and "frames stopped" in core.reason, core.reason

    stage.resume()
    core.start(RunSettings(estimate_timeout_s=5.0), "ref")
    core.tick()
    stage.stop("operator: controller hung test", by="request")  # the stop command reached the stage only
    clock.now += 6.5
    core.tick()
    assert core.state == "stopped" and "operator: controller hung test" in core.reason, core.reason

    # A stop of the stage's own (outputs it did not command) fails the run, saying why.
    stage.resume()
    core.start(RunSettings(estimate_timeout_s=5.0), "ref")
    core.tick()
    stage.stop("the amplifier's outputs changed while the serial link was down")
    clock.now += 0.2
    core.last_heartbeat = -math.inf  # the heartbeat is due
    core.tick()
    assert core.state == "failed" and "outputs changed" in core.reason, core.reason


def test_noise_near_the_target_is_not_divergence_however_small_the_tolerance(stage, tmp_path):
    """The dashboard's stop test once ended 'diverging': with tolerance 0.01 px the old
    floor (5 x tolerance)^2 counted estimation noise near the target as divergence.

    The content follows each move as commanded (a working stage): estimates that ignored
    the moves made the law learn, rightly, a stage that does not move; its moves grew
    with the time between frames, and a slow CI machine's reached the response check."""
    import time

    core = ControllerCore(LocalStage(stage), runs_dir=tmp_path)
    core.start(RunSettings(tolerance_px=0.01, max_iterations=1000), "ref")
    content = (0.0, 0.0)  # on the target
    for seq in range(1, 41):
        noise = 0.02 if seq % 4 else 0.4  # small errors, and now and then a noisy one
        record = core.on_estimate(estimate(seq, content[0] + noise, content[1] - noise,
                                           scan_started_at_ns=time.time_ns()))
        if record["action"] == "moved":
            content = as_commanded(content, record)
        if core.state != "servoing":
            break
    # Still servoing, or converged onto the noise's mean (0.1 px): never failed.
    assert core.state in ("servoing", "converged"), core.reason


def test_a_killed_controllers_run_is_finished_from_its_journal(stage, tmp_path):
    import time

    first = ControllerCore(LocalStage(stage), runs_dir=tmp_path)
    # The paper's law moves on each of these made-up estimates; the position law would end
    # the run on the second (the content did not follow its move: see the next test).
    first.start(RunSettings(law="paper"), "ref")
    for seq in (1, 2, 3):
        first.on_estimate(estimate(seq, 20.0, -10.0, scan_started_at_ns=time.time_ns()))
    run_id = first.run.id
    first._journal.flush()  # killed here: the journal is all that is left (no summary)
    assert not (tmp_path / f"{run_id}.json").exists()

    second = ControllerCore(LocalStage(stage), runs_dir=tmp_path)
    assert second.recover() == [run_id]
    record = second.stored(run_id)
    assert record["outcome"]["state"] == "failed" and record["outcome"]["recovered"]
    assert "controller stopped mid-run" in record["outcome"]["reason"]
    assert [r["seq"] for r in record["records"]] == [1, 2, 3] and record["iterations"] == 3
    assert any(entry["text"].startswith("set,") for entry in record["stage_log"]), "the stage's log, since the start"
    assert second.recover() == [], "recovered once"


def test_a_far_target_is_reached_in_chained_moves_within_the_stages_step_and_rate_limits(link, tmp_path):
    """Once the stage has moved the content as commanded, the position law asks for up to
    ``moves_per_frame`` x ``max_move_um`` on one frame; the controller writes it as that
    many commands, each within the step limit and waiting for the stage's settling and
    rate limit (the stage's real clock and default limits: nothing is refused)."""
    _, pty = link
    with connected(pty, settle_s={"x": 0.01, "y": 0.01}) as real:  # default limits, the real clock
        # Every way, and back: pieces equal in um are not in volts (the branches are curved).
        for seq, content in enumerate([(250.0, -40.0), (-250.0, 40.0), (40.0, 250.0), (-40.0, -250.0)]):
            core = ControllerCore(LocalStage(real), runs_dir=tmp_path)
            core.start(RunSettings(max_move_um=10.0, moves_per_frame=3), "ref")  # 45 um away at 177 nm/px
            moves_before = real.counters["moves"]
            time.sleep(0.2)  # the next frame: the last run's voltage steps are within the rate limit
            first = core.on_estimate(estimate(2 * seq + 1, *content, scan_started_at_ns=time.time_ns()))
            assert first["action"] == "moved" and first["pieces"] == 1
            assert math.hypot(*first["targets"].values()) == pytest.approx(10.0)
            time.sleep(0.2)
            chained = core.on_estimate(estimate(2 * seq + 2, *as_commanded(content, first),
                                                scan_started_at_ns=time.time_ns()))
            assert chained["action"] == "moved", chained["action"]
            assert chained["pieces"] == 3 and 20.0 < math.hypot(*chained["targets"].values()) <= 30.0 + 1e-9
            written = chained["pieces_written_at_ns"]
            assert written == sorted(written) and len(written) == 3
            assert real.counters["refused"] == 0 and real.counters["moves"] == moves_before + 4
            core.stop("next direction")
            if real.state == "stopped":
                real.resume()


def test_a_stage_that_settles_slowly_gets_the_rest_of_a_chained_move_on_the_next_frame(link, tmp_path):
    """A chained move's next command waits for the stage to settle, but not for longer
    than the controller may go without feeding the stage's watchdog: the rest of the
    move is left to the next fresh frame, and the law learns from the piece made."""
    _, pty = link
    with connected(pty, limits=StageLimits(max_rate_v_per_s=1e6), clock=FakeClock(),
                   settle_s={"x": 2.0, "y": 2.0}) as slow:
        core = ControllerCore(LocalStage(slow), runs_dir=tmp_path)
        core.start(RunSettings(max_move_um=10.0, moves_per_frame=3), "ref")
        content = (250.0, -40.0)
        first = core.on_estimate(estimate(1, *content, scan_started_at_ns=time.time_ns()))
        slow.clock.now += 2.5  # the rate limit's clock: the next frame, after the stage settled
        started = time.monotonic()
        chained = core.on_estimate(estimate(2, *as_commanded(content, first),
                                            scan_started_at_ns=first["command_settled_at_ns"] + 1))
        assert time.monotonic() - started < 1.0, "it did not wait the stage's 2 s"
        assert chained["action"] == "moved" and chained["pieces"] == 1
        assert math.hypot(*chained["targets"].values()) <= 10.0 + 1e-9 < math.hypot(*chained["move"].values())
        assert core.run.law._pending["move"] == {f"{axis}_um": value for axis, value in chained["targets"].items()}


def test_an_operators_stop_between_a_chained_moves_commands_holds_the_stage_and_ends_the_run_stopped(link, tmp_path):
    """The operator stops the stage (it holds at once) while the controller is between
    the commands of a chained move: the next command is refused, nothing more is
    written, and the run ends stopped, saying so."""
    _, pty = link
    with connected(pty, settle_s={"x": 0.01, "y": 0.01}) as real:

        class StoppedMidChain(LocalPort):
            moves = 0

            def call(self, command, request=None, /, **fields):
                reply = super().call(command, request, **fields)
                if command.name == "move":
                    self.moves += 1
                    if self.moves == 2:  # the chained move's first command: the operator stops
                        real.stop("operator pressed stop", by="request")
                return reply

        core = ControllerCore(StoppedMidChain(stage_handlers, real), runs_dir=tmp_path)
        core.start(RunSettings(max_move_um=10.0, moves_per_frame=3), "ref")
        content = (250.0, -40.0)
        first = core.on_estimate(estimate(1, *content, scan_started_at_ns=time.time_ns()))
        time.sleep(0.2)
        voltages = dict(real.voltages)
        chained = core.on_estimate(estimate(2, *as_commanded(content, first), scan_started_at_ns=time.time_ns()))
        assert chained["action"] == "refused by the stage: stopped"
        assert chained["pieces"] == 1 and chained["voltages"] == dict(real.voltages), "the record keeps what was made"
        assert core.state == "stopped" and core.reason == "operator pressed stop", core.reason
        assert real.state == "stopped" and real.counters["moves"] == 2, "one command of the chain, then none"
        assert real.voltages != voltages  # the first command was written before the stop


def test_the_position_law_ends_a_run_whose_content_does_not_follow_its_moves(stage, tmp_path):
    """A wrong camera-to-stage sign, a blocked axis or wrong estimates: the content does
    not move as commanded, twice in a row, and the run fails with the reason instead of
    moving again."""
    import time

    core = ControllerCore(LocalStage(stage), runs_dir=tmp_path)
    core.start(RunSettings(), "ref")
    actions = []
    for seq in range(1, 8):
        if core.state != "servoing":
            break
        stage.clock.now += 1.0  # the stage's rate limit: a second later
        time.sleep(0.01)  # each frame scanned after the last move has settled
        actions.append(core.on_estimate(estimate(seq, 20.0, -10.0, scan_started_at_ns=time.time_ns()))["action"])
    # Each move not seen is asked again on the next frame (a late move reads as none), then counts.
    asked_again = "held: the last move not seen yet (asked again on the next frame)"
    assert actions == ["moved", asked_again, "moved", asked_again, "held: unexpected response"], actions
    assert core.state == "failed" and "did not move as commanded" in core.reason, core.reason


def test_a_restarted_stage_comes_back_held_with_its_command_log(link, tmp_path):
    _, pty = link
    first = StageCore(pty.path, limits=StageLimits(max_rate_v_per_s=1e6), state_dir=tmp_path)
    assert first.connect() and first.state == "ready"
    first.arm(3.0, "controller-abc")
    first.move({"x": 1.0}, relative=True, owner="controller-abc")
    with pytest.raises(Refused) as refused:  # a jog from elsewhere during the run
        first.move({"x": 1.0}, relative=True, owner="gateway")
    assert refused.value.code == "owned"
    first.close()  # killed: no orderly shutdown

    second = StageCore(pty.path, limits=StageLimits(max_rate_v_per_s=1e6), state_dir=tmp_path)
    assert second.connect()
    assert second.state == "held" and "controller-abc" in second.state_reason
    assert any(entry["text"].startswith("set,") for entry in second.command_log()), "the log before the restart"
    with pytest.raises(Refused):
        second.move({"x": 0.5}, relative=True)
    second.arm(3.0, "controller-new")  # a new run claims it
    assert second.state == "ready"
    second.disarm("controller-new")
    second.shutdown()  # orderly, nothing armed: the next start is ready

    third = StageCore(pty.path, limits=StageLimits(max_rate_v_per_s=1e6), state_dir=tmp_path)
    assert third.connect() and third.state == "ready"
    third.shutdown()


def test_a_stop_holds_across_an_orderly_restart(link, tmp_path):
    _, pty = link
    first = StageCore(pty.path, limits=StageLimits(max_rate_v_per_s=1e6), state_dir=tmp_path)
    assert first.connect()
    first.stop("operator: the sample is loose")
    first.shutdown()  # orderly (compose down): the operator's stop is not forgotten

    second = StageCore(pty.path, limits=StageLimits(max_rate_v_per_s=1e6), state_dir=tmp_path)
    assert second.connect()
    assert second.state == "stopped" and second.state_reason == "operator: the sample is loose (before a restart)"
    with pytest.raises(Refused):
        second.move({"x": 0.5}, relative=True)
    second.resume()
    second.shutdown()

    third = StageCore(pty.path, limits=StageLimits(max_rate_v_per_s=1e6), state_dir=tmp_path)
    assert third.connect() and third.state == "ready"
    third.shutdown()


def test_outputs_the_stage_did_not_command_stop_it(link, tmp_path):
    world, pty = link
    clock = FakeClock()
    core = StageCore(pty.path, limits=StageLimits(max_rate_v_per_s=1e6), clock=clock)
    assert core.connect()
    core.move({"x": 1.0}, relative=True)
    commanded = core.voltages["x"]
    world.set_voltage(0, commanded + 5.0)  # the front-panel knob, or a second serial client
    clock.now += 2.0
    core.poll()
    assert core.state == "stopped" and "without a command" in core.state_reason
    assert core.voltages["x"] == pytest.approx(commanded + 5.0, abs=0.01)
    assert core.counters["uncommanded_changes"] == 1
    core.close()


def test_outputs_changed_while_the_link_was_down_stop_the_stage_on_reconnect(link):
    """A fake lab restarted (a new world at its home voltages), or an amplifier
    power-cycled: the reconnected stage is not where it was believed to be."""
    world, pty = link
    core = StageCore(pty.path, limits=StageLimits(max_rate_v_per_s=1e6))
    assert core.connect()
    core.move({"x": 2.0}, relative=True)
    core.close()  # the link drops ...
    world.set_voltage(0, core.voltages["x"] - 6.0)  # ... and the outputs change meanwhile
    assert core.connect()
    assert core.state == "stopped" and "while the serial link was down" in core.state_reason
    core.resume()
    assert core.connect() and core.state == "ready", "an unchanged amplifier reconnects without a stop"
    core.close()


def test_a_run_on_frames_without_a_pixel_size_fails_saying_which_setting_and_moves_nothing(stage, tmp_path):
    import time

    core = ControllerCore(LocalStage(stage), runs_dir=tmp_path)
    core.start(RunSettings(), "ref")
    before = dict(stage.voltages)
    unknown = estimate(1, 20.0, 5.0, scan_started_at_ns=time.time_ns()).model_copy(update={"pixel_size_nm": None})
    record = core.on_estimate(unknown)
    assert record["action"] == "held: pixel size unknown"
    assert core.state == "failed" and "SEMSERVO_IMAGESERVER__PIXEL_SIZE_NM" in core.reason
    assert stage.voltages == before
    assert core.status()["error_um"] is None


def test_a_move_refused_because_an_operator_stopped_the_stage_ends_the_run_stopped(stage, tmp_path):
    """The gateway's stop reaches the stage before the controller: a move in between is
    refused ("stopped"), and the run is recorded as stopped by the operator, not failed,
    with the operator's reason as it stands when the stop reaches the controller first
    (examples/hold_against_drift.py prints it; which came first once changed it)."""
    import time

    core = ControllerCore(LocalStage(stage), runs_dir=tmp_path)
    core.start(RunSettings(), "ref")
    stage.stop("operator pressed stop", by="request")  # as the stop command stops it
    record = core.on_estimate(estimate(1, 20.0, 5.0, scan_started_at_ns=time.time_ns()))
    assert record["action"] == "refused by the stage: stopped"
    assert core.state == "stopped" and core.reason == "operator pressed stop", core.reason


def test_a_move_refused_because_the_stage_stopped_itself_fails_the_run_saying_so(stage, tmp_path):
    """A stop of the stage's own (outputs it did not command, a link lost) that a move
    meets before the heartbeat does fails the run, as the heartbeat would: no operator
    stopped it."""
    import time

    core = ControllerCore(LocalStage(stage), runs_dir=tmp_path)
    core.start(RunSettings(), "ref")
    stage.stop("outputs moved without a command")
    record = core.on_estimate(estimate(1, 20.0, 5.0, scan_started_at_ns=time.time_ns()))
    assert record["action"] == "refused by the stage: stopped"
    assert core.state == "failed" and core.reason == "the stage stopped itself: outputs moved without a command", \
        core.reason


@pytest.fixture
def turning_stage(link):
    """The stage's core with the world's rotation-and-tilt stage as its rotation driver."""
    world, pty = link
    core = StageCore(pty.path, limits=StageLimits(max_rate_v_per_s=1e6, max_turn_deg=10.0), clock=FakeClock(),
                     rotation=WorldRotationStage(world))
    assert core.connect()
    yield core, world
    core.close()


def test_the_rotation_stage_turns_through_the_stage_and_its_rules(turning_stage):
    stage, world = turning_stage
    turned = stage.rotate({"rotation_deg": 2.5}, relative=True)
    # The stage turns at its own speed: the reply says where it is going and when it gets there.
    assert turned["targets_deg"]["rotation_deg"] == pytest.approx(2.5) == world.goniometer.targets()["rotation_deg"]
    assert turned["settled_at_ns"] > turned["written_at_ns"]
    stage.rotate({"rotation_deg": 0.5}, relative=True)  # relative to where it was sent, not to where it is yet
    assert world.goniometer.targets()["rotation_deg"] == pytest.approx(3.0)
    stage.rotate({"tilt_x_deg": -4.0})
    assert world.pose(world.now() + 5.0).rotation_deg == pytest.approx(3.0, abs=0.01)
    assert world.goniometer.targets() == {"rotation_deg": 3.0, "tilt_x_deg": -4.0, "tilt_y_deg": 0.0}
    for targets, relative, code in [
        ({"rotation_deg": float("nan")}, True, "rotation_limit"),
        ({"rotation_deg": float("inf")}, False, "rotation_limit"),
        ({"tilt_y_deg": 60.0}, False, "rotation_limit"),  # beyond the +-45 degree travel
        ({"rotation_deg": 15.0}, True, "step_limit"),  # more than max_turn_deg in one command
        ({"spin": 1.0}, True, "bad_axis"),
        ({"rotation_deg": 1.0, "tilt_y_deg": 99.0}, False, "rotation_limit"),  # refused whole
    ]:
        with pytest.raises(Refused) as refusal:
            stage.rotate(targets, relative=relative)
        assert refusal.value.code == code
    assert world.goniometer.targets() == {"rotation_deg": 3.0, "tilt_x_deg": -4.0, "tilt_y_deg": 0.0}, \
        "nothing more was commanded"


def test_a_stopped_or_owned_stage_does_not_turn(turning_stage):
    stage, world = turning_stage
    stage.arm(5.0, owner="run-1")
    with pytest.raises(Refused) as refusal:
        stage.rotate({"rotation_deg": 1.0}, relative=True, owner="someone-else")
    assert refusal.value.code == "owned"
    stage.rotate({"rotation_deg": 1.0}, relative=True, owner="run-1")
    stage.stop("operator")
    # A stop halts a turn on its way: the stage stays where the stop found it.
    halted = world.goniometer.targets()["rotation_deg"]
    assert 0.0 <= halted <= 1.0
    with pytest.raises(Refused) as refusal:
        stage.rotate({"rotation_deg": 1.0}, relative=True, owner="run-1")
    assert refusal.value.code == "stopped"
    assert world.goniometer.targets()["rotation_deg"] == halted


def test_a_lab_without_a_rotation_stage_says_so(stage):
    with pytest.raises(Refused) as refusal:
        stage.rotate({"rotation_deg": 1.0}, relative=True)
    assert refusal.value.code == "no_rotation_stage"
    assert stage.describe()["rotation"] is None


TiltingEstimator = FakeEstimator  # it accepts ``measure`` with tilts


def with_tilt(base: MotionEstimate, seq: int, alpha: float, beta: float, started_ns: int,
              confidence: float = 0.9) -> MotionEstimate:
    return base.model_copy(update={"alpha_deg": alpha, "beta_deg": beta, "tilt_confidence": confidence,
                                   "tilt_seq": seq, "tilt_scan_started_at_ns": started_ns, "tilt_frames": 9,
                                   "tilt_source_interval_s": (seq * 4.0, seq * 4.0 + 3.0)})


def test_the_tilts_are_servoed_once_per_fresh_sweep_and_saturated(turning_stage, tmp_path):
    import time

    stage, world = turning_stage
    estimator = TiltingEstimator()
    core = ControllerCore(LocalStage(stage), estimator=estimator, runs_dir=tmp_path)
    core.start(RunSettings(dofs=["x", "y", "gamma", "alpha", "beta"], converge_frames=1, max_turn_deg=2.0), "ref")
    assert ("measure", {"rotation": True, "tilts": True}) in estimator.asked
    assert core.settings.dofs == ["x", "y", "rotation", "alpha", "beta"], "gamma is the rotation about the beam"
    now = time.time_ns()
    first = core.on_estimate(with_tilt(estimate(1, 0.0, 0.0, scan_started_at_ns=now), 1, 12.0, -0.5, now))
    # A 12 degree tilt error: the move is saturated at max_turn_deg, with the right signs.
    assert first["tilt_action"] == "moved" and first["saturated"]
    assert first["turn_deg"]["tilt_x_deg"] == pytest.approx(-2.0) and 0 < first["turn_deg"]["tilt_y_deg"] < 2.0
    assert world.goniometer.targets()["tilt_x_deg"] == pytest.approx(-2.0)
    # The estimator is told of the tilt move and when it arrives: the sweep it is scanning
    # is stale, and the next starts once the tilt has settled.
    assert ("tilted", {"settles_at_ns": first["command_settled_at_ns"]}) in estimator.asked
    assert first["tilt_sweeps_restarted"] is True
    # And of the move's settling, for the frame it lands in: measured on its rows after it.
    assert ("moved", {"settles_at_ns": first["command_settled_at_ns"]}) in estimator.asked
    # The same sweep again does not move the tilts twice; a sweep scanned during the
    # tilt move is held.
    later = time.time_ns()
    again = core.on_estimate(with_tilt(estimate(2, 0.0, 0.0, scan_started_at_ns=later + 10**9), 1, 12.0, -0.5, now))
    assert "tilt_action" not in again and "tilt_x_deg" not in again.get("turn_deg", {})
    during = core.on_estimate(with_tilt(estimate(3, 0.0, 0.0, scan_started_at_ns=later + 2 * 10**9), 2, 10.0, -0.4,
                                        first["command_settled_at_ns"] - 1))
    assert during["tilt_action"].startswith("held: sweep scanned during")
    # Converged only once a fresh sweep says the tilts are within tolerance.
    assert core.state == "servoing"
    settled = max(first["command_settled_at_ns"], during.get("command_settled_at_ns", 0))
    done = core.on_estimate(with_tilt(estimate(4, 0.01, 0.0, scan_started_at_ns=settled + 10**9), 3, 0.04, -0.03,
                                      settled + 1))
    assert done["tilt_action"] == "within tolerance" and core.state == "converged", core.reason
    assert ("measure", {"rotation": None, "tilts": None}) in estimator.asked, "the estimator is told the run ended"


def test_a_tilt_move_decided_on_the_frame_the_run_converges_on_is_not_recorded_as_made(turning_stage, tmp_path):
    """Tilts within tolerance but over half of it: the tilt law decides a move, and the
    run converges on the same frame (x, y, gamma and the tilts within tolerance), so the
    move is not made. The record says so: a "moved" there was counted as the run's last
    move (where its stage came to rest) and as a tilt move the estimator was not told of."""
    import time

    from semservo.runs import resting_frames

    stage, world = turning_stage
    estimator = TiltingEstimator()
    core = ControllerCore(LocalStage(stage), estimator=estimator, runs_dir=tmp_path)
    core.start(RunSettings(dofs=["x", "y", "gamma", "alpha", "beta"], converge_frames=1, tolerance_tilt_deg=0.1), "ref")
    before = world.goniometer.targets()
    now = time.time_ns()
    done = core.on_estimate(with_tilt(estimate(1, 0.01, 0.0, scan_started_at_ns=now), 1, 0.08, -0.02, now))
    assert core.state == "converged", core.reason
    assert done["tilt_action"] == f"not moved: {done['action']}"
    assert world.goniometer.targets() == before and not any(command == "tilted" for command, _ in estimator.asked)
    assert resting_frames(core.run.records) == [core.run.records[-1]]


def test_an_estimator_that_does_not_hear_of_a_tilt_move_costs_time_not_the_run(turning_stage, tmp_path):
    """Telling the estimator of a tilt move only saves the sweep it is scanning: an
    estimator that does not answer it leaves the run servoing (that sweep is then held
    as stale when it comes), recorded as not restarted."""
    from semservo.errors import ServiceUnavailable

    stage, _ = turning_stage

    class Deaf(TiltingEstimator):
        def call(self, command, request=None, /, **fields):
            if command is estimator_protocol.TILTED:
                raise ServiceUnavailable("the estimator service does not answer")
            return super().call(command, request, **fields)

    core = ControllerCore(LocalStage(stage), estimator=Deaf(), runs_dir=tmp_path)
    core.start(RunSettings(dofs=["x", "y", "alpha", "beta"], converge_frames=1, max_turn_deg=2.0), "ref")
    now = time.time_ns()
    moved = core.on_estimate(with_tilt(estimate(1, 0.0, 0.0, scan_started_at_ns=now), 1, 3.0, -1.0, now))
    assert moved["tilt_action"] == "moved" and moved["tilt_sweeps_restarted"] is False
    assert core.state == "servoing"
    core.stop("test done")


def test_a_tilt_run_without_a_taught_sweep_is_refused(turning_stage, tmp_path):
    stage, _ = turning_stage

    class NoSweep(TiltingEstimator):
        def call(self, command, request=None, /, **fields):
            if command is estimator_protocol.MEASURE and fields.get("tilts"):
                raise CommandError("no_tilt_reference", "no tilt reference: teach with tilts=true first")
            return super().call(command, request, **fields)

    core = ControllerCore(LocalStage(stage), estimator=NoSweep(), runs_dir=tmp_path)
    with pytest.raises(CommandError, match="teach with tilts=true") as refusal:
        core.start(RunSettings(dofs=["x", "y", "alpha"]), "ref")
    assert refusal.value.code == "no_tilt_reference", "the state's conflict (409), not a malformed request"
    assert core.state == "idle" and stage.watchdog.owner is None


def test_a_run_start_waits_for_an_estimator_busy_past_the_loops_timeouts(turning_stage, tmp_path, context):
    """Over real sockets, as the controller process wires them (``estimator_ports``): an
    estimator that answers a start's ``measure`` past the loop's 2 tries of 1 s (busy
    after a teach on a loaded machine) still starts the run, where the loop's own port
    refuses it, saying so, with nothing armed."""
    import threading
    import time

    from semservo.errors import BadRequest
    from semservo.transport import ControlClient, ControlServer
    from services.controller.main import estimator_ports
    from tests.conftest import serve_until

    stage, _ = turning_stage
    server = ControlServer("tcp://127.0.0.1:*", max_message_bytes=65536, context=context)
    busy_for_s = [2.5]  # the first request only

    def measure(args: dict) -> dict:
        time.sleep(busy_for_s.pop() if busy_for_s else 0.0)
        return {"rotation": bool(args.get("rotation")), "tilts": bool(args.get("tilts"))}

    server.register("measure", measure)
    stop = threading.Event()
    thread = threading.Thread(target=serve_until, args=(server, stop), daemon=True)
    thread.start()
    client = ControlClient(server.endpoint, timeout_s=1.0, retries=2, context=context)
    try:
        loop_port, start_port = estimator_ports(client)
        core = ControllerCore(LocalStage(stage), estimator=loop_port, estimator_at_start=start_port,
                              runs_dir=tmp_path)
        core.start(RunSettings(dofs=["x", "y", "rotation"]), "ref")
        assert core.state == "servoing" and stage.watchdog.owner == core.owner
        core.stop("test over")
        stage.resume()
        busy_for_s.append(2.5)
        impatient = ControllerCore(LocalStage(stage), estimator=loop_port, runs_dir=tmp_path)
        with pytest.raises(BadRequest, match="rotation cannot be servoed: the estimator, which measures it, did not "
                                             "take the request"):
            impatient.start(RunSettings(dofs=["x", "y", "rotation"]), "ref")
        assert impatient.state == "idle" and stage.watchdog.owner is None
    finally:
        stop.set()
        thread.join()
        client.close()
        server.close()


def test_a_tilts_only_run_waits_for_its_sweeps(turning_stage, tmp_path):
    import time

    stage, world = turning_stage
    core = ControllerCore(LocalStage(stage), estimator=TiltingEstimator(), runs_dir=tmp_path)
    core.start(RunSettings(dofs=["alpha", "beta"], converge_frames=1), "ref")
    now = time.time_ns()
    waiting = core.on_estimate(estimate(1, 5.0, 5.0, scan_started_at_ns=now))  # no sweep yet: x, y are not servoed
    assert waiting["action"] == "held: waiting for a focus sweep" and core.state == "servoing"
    moved = core.on_estimate(with_tilt(estimate(2, 5.0, 5.0, scan_started_at_ns=now), 1, 1.0, -0.5, now))
    assert moved["action"] == "moved" and set(moved["turn_deg"]) == {"tilt_x_deg", "tilt_y_deg"}
    later = moved["command_settled_at_ns"] + 1
    done = core.on_estimate(with_tilt(estimate(3, 5.0, 5.0, scan_started_at_ns=later), 2, 0.02, 0.01, later))
    assert core.state == "converged" and done["tilt_action"] == "within tolerance", "x, y do not count here"
