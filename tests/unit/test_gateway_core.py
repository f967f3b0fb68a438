"""The gateway's core without sockets: ports are small fakes that answer as the services
do (their replies checked against the same models), so the rules the REST API relies on
are checked one by one."""

from __future__ import annotations

import numpy as np
import pytest

from semservo.errors import CommandError, ServiceUnavailable, http_status
from services.gateway.core import GatewayCore
from services.gateway.records import RunStore

STAGE_STATE = {"url": "socket://x", "link": "connected", "state": "ready", "reason": "", "device": "NV40/3",
               "voltages": {"x": 40.0}, "positions_um": {"x": 20.0},
               "limits": {"voltage_min": -19, "voltage_max": 110, "travel_min_um": 0, "travel_max_um": 100,
                          "max_step_v": 25, "max_rate_v_per_s": 200, "max_turn_deg": 30, "device_voltage": [-20, 130]},
               "watchdog": {"armed": False, "timeout_s": 0, "owner": None}, "models": {"x": "branches"},
               "rotation": None, "last_error": None, "moves": 0, "turns": 0, "refused": 0, "link_lost": 0,
               "reconnects": 0, "uncommanded_changes": 0}
MOVED = {"written_at_ns": 1, "voltages": {"x": 40.0}, "positions_um": {"x": 20.0}}
REFERENCE = {"id": "ref", "kind": "frame", "shape": [512, 512], "pixel_size_nm": 177.0, "taught_at_ns": 1}


def controller_status(state: str = "idle", run_id: str | None = None) -> dict:
    return {"state": state, "run_id": run_id}


class Port:
    """A service's port: answers from a table by command name (or raises what the table
    holds), each answer read through the command's reply model as the real port does."""

    def __init__(self, **answers):
        self.answers = answers
        self.asked: list[tuple[str, dict]] = []

    def call(self, command, request=None, /, **fields):
        built = command.build(request, **fields)
        self.asked.append((command.name, built.model_dump(exclude_defaults=True)))
        answer = self.answers[command.name]
        if callable(answer):
            answer = answer()
        if isinstance(answer, Exception):
            raise answer
        return command.reply.model_validate(answer)


def core_with(**ports) -> GatewayCore:
    return GatewayCore(ports, RunStore(":memory:"))


def test_a_jog_waits_out_the_stages_rate_rule():
    refusals = [CommandError("rate_limit", "x: 10 V 3 ms after the last write"),
                CommandError("rate_limit", "x: 10 V 40 ms after the last write")]
    stage = Port(move=lambda: refusals.pop(0) if refusals else MOVED)
    core = core_with(stage=stage, controller=Port(status=controller_status()))
    assert core.move({"x": 10.0}, relative=True).voltages == {"x": 40.0}
    assert [command for command, _ in stage.asked] == ["move", "move", "move"]


def test_a_jog_during_a_run_is_refused_before_the_stage_is_asked():
    stage = Port(move=MOVED)
    core = core_with(stage=stage, controller=Port(status=controller_status("servoing", "r1")))
    with pytest.raises(CommandError) as refused:
        core.move({"x": 1.0}, relative=True)
    assert http_status(refused.value.code) == 409
    assert refused.value.code == "run_active" and refused.value.extra["run_id"] == "r1"
    assert stage.asked == []


def test_a_start_never_resumes_a_stopped_stage_unless_told():
    stage = Port(state={**STAGE_STATE, "state": "stopped", "reason": "operator"},
                 resume={**STAGE_STATE, "state": "ready"})
    controller = Port(status=controller_status("stopped"), start={"run_id": "r2", "state": "servoing"},
                      run={"id": "r2", "started_at_ns": 1, "settings": {}})
    core = core_with(stage=stage, controller=controller)
    with pytest.raises(CommandError) as refused:
        core.start({})
    assert refused.value.code == "stage_stopped" and ("resume", {}) not in stage.asked
    assert core.start({}, resume=True)["run_id"] == "r2"
    assert ("resume", {}) in stage.asked


def test_a_teach_waits_for_the_frames_it_averages():
    counts = iter([1, 2, 3])

    def teach():
        have = next(counts, None)
        if have is not None:
            return CommandError("not_enough_frames", f"only {have} frames received so far; 4 asked for averaging")
        return REFERENCE

    estimator = Port(report={"reference": None, "rotation": True, "measure_rotation": True, "measure_tilts": False,
                             "tilt_reference": None, "last_tilt": None, "tilt_error": None, "precision": "full",
                             "latest_frame_seq": 3, "last_estimate": None},
                     teach=teach, reference_image=CommandError("no_reference", "not in this test"))
    core = core_with(estimator=estimator, controller=Port(status=controller_status()))
    assert core.teach(frames=4)["id"] == "ref"
    assert [name for name, _ in estimator.asked].count("teach") == 4


def test_a_dead_controller_does_not_block_a_teach():
    """No controller, no run: the stage's own rules still hold, so the teach goes on."""
    estimator = Port(report={"reference": None, "rotation": True, "measure_rotation": True, "measure_tilts": False,
                             "tilt_reference": None, "last_tilt": None, "tilt_error": None, "precision": "full",
                             "latest_frame_seq": 3, "last_estimate": None},
                     teach=REFERENCE, reference_image=CommandError("no_reference", "not in this test"))
    core = core_with(estimator=estimator, controller=Port(status=ServiceUnavailable("no reply")))
    assert core.teach()["id"] == "ref"


def test_one_teach_at_a_time_and_no_start_or_jog_meanwhile():
    """A second teach while one waits for its frames is refused (409), as are a start and a
    jog (a run would begin on the old reference; a jog would blend the averaged frames);
    both answer again once the teach has."""
    import threading

    asked_to_teach, release = threading.Event(), threading.Event()

    def teach():
        asked_to_teach.set()
        release.wait(10)
        return REFERENCE

    estimator = Port(report={"reference": None, "rotation": True, "measure_rotation": True, "measure_tilts": False,
                             "tilt_reference": None, "last_tilt": None, "tilt_error": None, "precision": "full",
                             "latest_frame_seq": 3, "last_estimate": None},
                     teach=teach, reference_image=CommandError("no_reference", "not in this test"))
    stage = Port(move=MOVED, state=STAGE_STATE)
    controller = Port(status=controller_status(), start={"run_id": "r1", "state": "servoing"},
                      run={"id": "r1", "started_at_ns": 1, "settings": {}})
    core = core_with(estimator=estimator, stage=stage, controller=controller)
    first: dict = {}
    teacher = threading.Thread(target=lambda: first.update(core.teach()))
    teacher.start()
    try:
        assert asked_to_teach.wait(10)
        for attempt, refused_what in ((lambda: core.teach(frames=2), "teaching"),
                                      (lambda: core.start({}), "starting a run"),
                                      (lambda: core.move({"x": 1.0}, relative=True), "moving the stage")):
            with pytest.raises(CommandError) as refused:
                attempt()
            assert refused.value.code == "teach_in_progress" and http_status(refused.value.code) == 409
            assert refused.value.message.startswith(f"{refused_what} refused: a teach is under way")
    finally:
        release.set()
        teacher.join(10)
    assert first["id"] == "ref"
    assert [name for name, _ in estimator.asked].count("teach") == 1
    assert "move" not in [name for name, _ in stage.asked]
    assert core.move({"x": 1.0}, relative=True).voltages == {"x": 40.0}
    assert core.start({})["run_id"] == "r1"


def test_a_service_that_does_not_answer_is_a_503_naming_it():
    core = core_with(stage=Port(state=ServiceUnavailable("no reply after 1 tries")))
    with pytest.raises(CommandError) as refused:
        core.stage_state()
    assert refused.value.code == "stage_unavailable" and http_status(refused.value.code) == 503
    assert "the stage service does not answer" in refused.value.message


def test_click_to_move_on_frames_without_a_pixel_size_is_refused_not_guessed():
    import numpy as np

    from semservo.wire import Frame, frame_header

    stage = Port(move=MOVED)
    core = core_with(stage=stage, controller=Port(status=controller_status()))
    pixels = np.zeros((64, 64), np.uint8)
    core.latest = Frame(header=frame_header(pixels, seq=1, acquired_at_ns=1, source="watch"), pixels=pixels)
    with pytest.raises(CommandError) as refused:
        core.center(10.0, 20.0)
    assert http_status(refused.value.code) == 409 and refused.value.code == "pixel_size_unknown"
    assert stage.asked == []


def test_a_tilted_runs_truth_is_the_error_the_image_shows_not_the_stages_alone():
    """With the tilt cradle tilted, x, y make up for the pivot's lever: the stage's own x, y
    end away from the taught ones while the view is on target. The truth a run reports is
    then the view's (the content at the taught centre), beside the stage's."""
    from services.gateway.core import view_error_px

    taught = {"x_um": 0.0, "y_um": 0.0, "rotation_deg": 0.0, "tilt_x_deg": 0.0, "tilt_y_deg": 0.0}
    assert view_error_px({"x_um": 0.5, "y_um": 0.0}, {"x_um": 0.0, "y_um": 0.0}, 0.1) is None  # no tilts: one error
    # Equal tilts: the view's error is the stage's.
    tilted = {**taught, "tilt_x_deg": 2.0}
    view = view_error_px({**tilted, "x_um": 0.5}, tilted, 0.1)
    assert np.hypot(*view) == pytest.approx(5.0, rel=0.02)
    # A residual tilt moves the view by the pivot's lever: the stage at the taught x, y is
    # not on target, and the view error says by how much.
    lever = view_error_px({**taught, "tilt_x_deg": 0.2}, taught, 0.1)
    assert np.hypot(*lever) > 0.5


def test_a_finished_runs_report_is_drawn_once_and_anew_when_its_record_changes(monkeypatch):
    import services.gateway.report as report

    drawn = []
    monkeypatch.setattr(report, "report_png", lambda run: drawn.append(run["state"]) or f"png {len(drawn)}".encode())
    core = core_with()
    run = {"id": "r1", "state": "converged", "iterations": 2, "outcome": {"reason": "within 0.1 px"},
           "trajectory": [{"iteration": 1}, {"iteration": 2}]}
    assert core.run_report(run) == core.run_report(dict(run)) == b"png 1"
    assert core.run_report({**run, "iterations": 3, "trajectory": [*run["trajectory"], {"iteration": 3}]}) == b"png 2"
    servoing = {**run, "id": "r2", "state": "servoing"}
    assert core.run_report(servoing) == b"png 3" and core.run_report(servoing) == b"png 4"  # still changing: drawn
    assert drawn == ["converged", "converged", "servoing", "servoing"]


def test_the_status_right_after_a_stop_says_stopped():
    """The status is built from the services' health, cached a quarter second for the
    dashboards: a script reading it right after its /stop saw 'servoing' for 20-65 ms.
    A stop (a start, a resume) drops the cache."""
    run = {"state": "servoing", "run_id": "r1"}

    def health(service):
        return lambda: {"service": service, "state": "running", "pid": 1, "uptime_s": 1.0, "counters": {},
                        "details": dict(run) if service == "controller" else {}}

    def stopped():
        run["state"] = "stopped"
        return {**run, "reason": "operator"}

    clock = [100.0]
    core = core_with(stage=Port(stop=STAGE_STATE, health=health("stage")),
                     controller=Port(stop=stopped, health=health("controller"),
                                     run={"id": "r1", "started_at_ns": 1, "settings": {}}))
    core.clock = lambda: clock[0]  # no time passes: the cache would still serve
    assert core.status()["state"] == "servoing"
    assert core.stop("operator")["state"] == "stopped"
    assert core.status()["state"] == "stopped"


def test_the_truth_is_not_asked_of_a_simulated_lab_known_to_be_down():
    """With the fake lab down after a run, every /status (its reconcile asks for a pending
    truth each second) waited out a pose request: 15-27 s, and clients timed out. The
    health just asked says it is down: the truth stays pending, nobody waits."""
    fakelab = Port(health=ServiceUnavailable("no answer"), pose=ServiceUnavailable("no answer"))
    core = core_with(fakelab=fakelab)
    core.store.save_reference(REFERENCE, {"x_um": 1.0, "y_um": 2.0, "world_id": "w"}, 1)
    record = {"reference_id": "ref", "settings": {"law": "paper"},
              "records": [{"frame_source_interval_s": [1.0, 1.5], "action": "moved", "pixel_size_nm": 177.0}]}
    core.health()
    truth, note, retry = core._true_final_error(record)
    assert truth is None and retry and "the simulated lab is down" in note
    assert "pose" not in [command for command, _ in fakelab.asked]
    fakelab.answers["health"] = {"service": "fakelab", "state": "running", "pid": 1, "uptime_s": 1.0, "counters": {}, "last_error": None,
                                 "details": {}}
    core.forget_health()
    core.health()
    core._true_final_error(record)
    assert "pose" in [command for command, _ in fakelab.asked], "asked again once it answers"
