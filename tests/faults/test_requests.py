"""Bad input and concurrency against the real stack: what the issue's reliability engineer
tried, each answered in words, nothing hanging, the stage never moved by a refusal."""

from __future__ import annotations

import math
import socket
import subprocess
import sys
import time

import pytest

from semservo.client import SemservoError, WaitTimeout
from semservo.transport import CommandError

pytestmark = pytest.mark.integration


def running(campaign, **settings) -> str:
    run_id = campaign.displaced_run(hold=True, tolerance_px=0.1, **settings)
    campaign.wait_for(lambda: campaign.iterations(run_id) >= 2, 60, "two iterations")
    return run_id


def test_teach_and_jog_during_a_run_are_refused_and_the_run_goes_on(campaign):
    lab = campaign.client
    run_id = running(campaign)
    for attempt in (lambda: lab.teach(), lambda: lab.move(x_um=5.0),
                    lambda: lab.http.post("/stage/center", json={"x_px": 10, "y_px": 10}).raise_for_status()):
        with pytest.raises(Exception) as refused:
            attempt()
        error = refused.value
        status = getattr(error, "status", None) or error.response.status_code
        assert status == 409, error
    # The stage itself refuses a move from anyone but the run's controller.
    with pytest.raises(CommandError, match="owned"):
        campaign.ask("stage", "move", targets={"x": 1.0}, relative=True, owner="someone-else")
    at = campaign.iterations(run_id)
    campaign.wait_for(lambda: campaign.iterations(run_id) > at, 30, "the run going on")
    lab.stop("test over")
    assert campaign.wait_finished(run_id)["state"] == "stopped"


def test_a_start_after_a_stop_does_not_resume_the_stage_silently(campaign):
    lab = campaign.client
    run_id = running(campaign)
    lab.stop("operator stop")
    campaign.wait_finished(run_id)
    assert lab.stage()["state"] == "stopped"
    with pytest.raises(SemservoError) as refused:
        lab.start()
    assert refused.value.status == 409 and refused.value.code == "stage_stopped"
    assert "resume" in refused.value.message
    assert lab.stage()["state"] == "stopped"
    started = lab.start(resume=True, tolerance_px=0.5)  # the operator's word
    lab.wait(started["run_id"], timeout=60)


def test_a_stop_with_a_body_it_cannot_read_stops_all_the_same(campaign):
    """A stop is never refused: a reason of the wrong type, a misspelt field, a body that
    is not JSON or too long a reason each stop the run and the stage, and say what was not
    used (each once answered 422 and left the run going)."""
    http = campaign.client.http
    bodies = {'{"reason": 123}': "not a string", '{"reasn": "typo"}': "unknown fields ignored: reasn",
              "not json": "not JSON", '{"reason": "' + "x" * 300 + '"}': "cut to 200",
              "[" * 3000: "not JSON", '{"reason": "\\ud800"}': "characters that are not text replaced",
              "{" + " " * 20_000 + "}": "over 16384 bytes"}
    for body, said in bodies.items():
        run_id = running(campaign)
        response = http.post("/stop", content=body, headers={"content-type": "application/json"})
        assert response.status_code == 200, (body, response.text)
        stopped = response.json()
        assert stopped["stage_stopped"] and said in stopped["body_ignored"], stopped
        assert campaign.wait_finished(run_id)["state"] == "stopped"
        stage = campaign.client.stage()
        assert stage["state"] == "stopped" and stage["stopped_by"] == "request", stage
        campaign.client.resume()
    # A stop with no body, or a proper one, has nothing to say about it.
    for kwargs in ({}, {"json": {"reason": "operator"}}):
        response = http.post("/stop", **kwargs)
        assert response.status_code == 200 and response.json()["body_ignored"] is None, response.text
    campaign.client.resume()


def semservo_cli(*arguments: str) -> subprocess.CompletedProcess:
    """The command line, against the stack (its ports are in this process's environment)."""
    return subprocess.run([sys.executable, "-m", "semservo", *arguments], capture_output=True, text=True, timeout=60)


def test_a_teach_from_the_command_line_during_a_run_is_refused_and_semservo_stop_stops_it(campaign):
    """`semservo teach` refuses while a run servos, as the gateway does (it once taught,
    and the run failed); `semservo stop` stops the stage and the run without the gateway."""
    run_id = running(campaign)
    reference = campaign.client.reference().id
    teach = semservo_cli("teach", "--frames", "1")
    assert teach.returncode == 1 and "refused" in teach.stderr and run_id in teach.stderr, teach.stderr
    assert campaign.client.reference().id == reference
    assert campaign.client.status().state == "servoing"
    stop = semservo_cli("stop", "--reason", "from the terminal")
    assert stop.returncode == 0, stop.stdout + stop.stderr
    assert "stage: stopped" in stop.stdout and run_id in stop.stdout, stop.stdout
    record = campaign.wait_finished(run_id)
    assert record["state"] == "stopped" and "from the terminal" in record["reason"], record["reason"]
    assert campaign.client.stage()["state"] == "stopped"
    campaign.client.resume()


def test_a_script_that_gives_up_waiting_stops_its_own_run_and_no_other(campaign):
    client = campaign.client
    run_id = running(campaign)
    with pytest.raises(WaitTimeout, match="it was stopped"):
        client.wait(run_id, timeout=1.0, stop_on_timeout=True)
    assert campaign.wait_finished(run_id)["state"] == "stopped"
    client.resume()
    other = running(campaign)
    # A run id this script got wrong: said at once, not waited out (nobody started it),
    # and another script's run goes on.
    with pytest.raises(SemservoError) as wrong:
        client.wait("20260101-000000-abcdef", timeout=60.0, stop_on_timeout=True)
    assert wrong.value.status == 404 and wrong.value.code == "no_such_run"
    assert client.status().state == "servoing" and client.status().run_id == other
    client.stop("test over")
    assert campaign.wait_finished(other)["state"] == "stopped"
    client.resume()


def test_a_json_body_to_teach_is_refused_in_words(campaign):
    response = campaign.client.http.post("/teach", json={"frames": 4})
    assert response.status_code == 415
    assert "query parameters" in response.json()["error"]["message"]


def test_huge_offsets_and_non_finite_numbers_are_4xx(campaign):
    http = campaign.client.http
    assert http.get("/runs", params={"offset": 9223372036854775808}).status_code == 422
    assert http.get("/runs", params={"offset": 2**63 - 1}).status_code == 422
    for body in ('{"x_um": NaN}', '{"x_um": Infinity}', '{"x_um": 1e999}', "{}"):
        response = http.post("/stage/move", content=body, headers={"content-type": "application/json"})
        assert response.status_code == 422, (body, response.text)
    for body in ('{"gain_scale": Infinity}', '{"tolerance_px": NaN}', '{"estimate_timeout_s": 1e999}',
                 '{"gain_scale": 1e308}', '{"law": "paper", "gain_min": 0.9, "gain_max": 0.1}'):
        response = http.post("/start", content=body, headers={"content-type": "application/json"})
        assert response.status_code == 422, (body, response.text)
    assert "gain_min (0.9) is above gain_max (0.1)" in response.json()["error"]["message"]
    response = http.post("/stage/center", json={"x_px": 90_000, "y_px": 3})
    assert response.status_code == 409 and response.json()["error"]["code"] == "outside_image"


def test_a_reference_taught_behind_the_runs_back_fails_it_at_once(campaign):
    run_id = running(campaign)
    taught = time.monotonic()
    campaign.ask("estimator", "teach", frames=1)  # not through the gateway: nothing refused it
    run = campaign.wait_finished(run_id, timeout_s=15)
    assert run["state"] == "failed" and "reference changed" in run["reason"], run["reason"]
    assert time.monotonic() - taught < 5


def test_a_second_client_on_the_amplifier_is_noticed_and_stops_the_stage(campaign):
    lab = campaign.client
    before = lab.stage()["voltages"]["x"]
    target = before + 7.0
    with socket.create_connection((campaign.settings.fakelab.host, campaign.settings.fakelab.serial_tcp_port)) as knob:
        knob.sendall(f"set,0,{target:.3f}\r".encode())
        time.sleep(0.2)
    stage = campaign.wait_for(lambda: (state := lab.stage())["state"] == "stopped" and state, 5,
                              "the stage to notice the change")
    assert stage["voltages"]["x"] == pytest.approx(target, abs=0.01), "GET /stage reports what the amplifier does"
    assert "without a command" in stage["reason"]
    assert stage["uncommanded_changes"] >= 1
    lab.http.post("/stage/resume").raise_for_status()


POISON = [math.nan, math.inf, -math.inf, 1e308, -1e308, 2**70, -(2**70), "x", None, [], {}, True, [math.nan] * 3]

#: Every command each service answers, and the arguments it takes.
COMMANDS = {
    "fakelab": {"info": [], "pose": ["t_s", "interval_s"], "set_rotation_stage": ["rotation_deg", "tilt_x_deg",
                                                                                  "tilt_y_deg", "halt"],
                "set_preset": ["preset"], "serial_link": ["plugged"]},
    "imageserver": {"info": [], "set_fps": ["fps"], "scan_once": ["dwell_ns", "magnification"],
                    "set_scan": ["dwell_ns", "magnification", "working_distance_mm", "working_distance_um"],
                    "start_sweep": ["working_distances_um"], "sweep": ["sweep_id"]},
    "estimator": {"teach": ["frames", "image_b64", "path", "polygon", "mask_b64", "tilts"], "clear": [], "report": [],
                  "measure": ["rotation", "tilts"]},
    "stage": {"state": [], "move": ["targets", "relative", "owner"], "rotate": ["targets", "relative", "owner"],
              "set_voltages": ["voltages", "owner"],
              "arm": ["hold_after_s", "owner"], "disarm": ["owner"], "heartbeat": ["owner"], "log": ["since_ns"]},
    "controller": {"status": [], "run": ["id"], "start": ["tolerance_px", "gain_scale", "max_move_um", "dofs",
                                                          "estimate_timeout_s", "tolerance_tilt_deg", "max_turn_deg"]},
}


def arguments(names: list[str]):
    yield {}
    for name in names:
        for value in POISON:
            yield {name: value}
            if name in ("targets", "voltages"):
                yield {name: {"x": value}}
            if name == "targets":
                yield {name: {"rotation_deg": value}}
            if name == "polygon":
                yield {name: [[value, 1], [2, 3], [4, 5]]}


def test_garbage_and_nan_on_every_control_socket(campaign):
    lab = campaign.client
    voltages = lab.stage()["voltages"]
    angles = campaign.ask("fakelab", "pose")["rotation_deg"]
    answered, internal = 0, []
    for service, commands in COMMANDS.items():
        client = campaign.control(service, timeout_s=30)
        try:
            for raw in (b"", b"\xff\xfe garbage", b'{"v": 1, "command": "health", "args": [1]}', b"[]", b"null",
                        b'{"v": 99, "command": "health"}', b'{"v": 1, "command": "no_such"}', b"{" * 10_000):
                client.request_raw(raw)
                answered += 1
            for command, names in commands.items():
                for args in arguments(names):
                    if command == "teach" and not args:
                        continue  # a valid teach: not what this test is about
                    try:
                        client.request(command, **args)
                    except CommandError as error:
                        if error.code == "internal":
                            internal.append((service, command, args, error.message))
                    answered += 1
        finally:
            client.close()
        assert campaign.healthy(service), f"{service} is not healthy after the barrage"
    assert not internal, internal
    assert answered > 500
    # Nothing the barrage sent moved the stage (a bad set point is refused whole).
    assert lab.stage()["voltages"] == pytest.approx(voltages, abs=0.01)
    assert campaign.ask("fakelab", "pose")["rotation_deg"] == angles
    assert lab.status()["frame_rate"] > 0  # the simulated SEM still scans
    campaign.ask("fakelab", "serial_link", plugged=True)
    campaign.ask("fakelab", "set_preset", preset="optimal")
    campaign.ask("imageserver", "set_fps", fps=30)
    assert campaign.next_run_converges()


def test_a_teach_right_after_a_start_waits_for_the_frames_it_averages(campaign):
    """`./dev demo` on a cold machine taught 4 averaged frames before 4 had arrived (422)."""
    campaign.launcher.restart_service("estimator")  # its frame buffer starts empty
    taught = campaign.client.teach(frames=16)
    assert taught["detail"]["frames_averaged"] == 16
