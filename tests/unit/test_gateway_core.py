"""The gateway's core without sockets: ports are small fakes that answer as the services
do, so the rules the REST API relies on are checked one by one."""

from __future__ import annotations

import pytest

from semservo.transport import CommandError, ServiceUnavailable
from services.gateway.core import GatewayCore, GatewayError
from services.gateway.records import RunStore


class Port:
    """A service's port: answers from a table, or raises what the table holds."""

    def __init__(self, **answers):
        self.answers = answers
        self.asked: list[tuple[str, dict]] = []

    def request(self, command: str, args: dict | None = None) -> dict:
        self.asked.append((command, args or {}))
        answer = self.answers[command]
        if callable(answer):
            answer = answer()
        if isinstance(answer, Exception):
            raise answer
        return answer


def core_with(**ports) -> GatewayCore:
    return GatewayCore(ports, RunStore(":memory:"))


def test_a_jog_waits_out_the_stages_rate_rule():
    refusals = [CommandError("rate_limit", "x: 10 V 3 ms after the last write"),
                CommandError("rate_limit", "x: 10 V 40 ms after the last write")]
    stage = Port(move=lambda: refusals.pop(0) if refusals else {"voltages": {"x": 40.0}})
    core = core_with(stage=stage, controller=Port(status={"state": "idle"}))
    assert core.move({"x": 10.0}, relative=True) == {"voltages": {"x": 40.0}}
    assert [command for command, _ in stage.asked] == ["move", "move", "move"]


def test_a_jog_during_a_run_is_refused_before_the_stage_is_asked():
    stage = Port(move={"voltages": {}})
    core = core_with(stage=stage, controller=Port(status={"state": "servoing", "run_id": "r1"}))
    with pytest.raises(GatewayError) as refused:
        core.move({"x": 1.0}, relative=True)
    assert refused.value.status == 409 and refused.value.code == "run_active" and refused.value.extra["run_id"] == "r1"
    assert stage.asked == []


def test_a_start_never_resumes_a_stopped_stage_unless_told():
    stage = Port(state={"state": "stopped", "reason": "operator"}, resume={"state": "ready"})
    controller = Port(status={"state": "stopped"}, start={"run_id": "r2", "state": "servoing"},
                      run={"id": "r2", "started_at_ns": 1, "settings": {}})
    core = core_with(stage=stage, controller=controller)
    with pytest.raises(GatewayError) as refused:
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
        return {"id": "ref", "kind": "frame", "shape": [512, 512], "pixel_size_nm": 177.0}

    core = core_with(estimator=Port(health={}, teach=teach), controller=Port(status={"state": "idle"}))
    assert core.teach(frames=4)["id"] == "ref"


def test_a_dead_controller_does_not_block_a_teach():
    """No controller, no run: the stage's own rules still hold, so the teach goes on."""
    core = core_with(estimator=Port(health={}, teach={"id": "ref", "kind": "frame", "shape": [8, 8],
                                                      "pixel_size_nm": 1.0}),
                     controller=Port(status=ServiceUnavailable("no reply")))
    assert core.teach()["id"] == "ref"


def test_click_to_move_on_frames_without_a_pixel_size_is_refused_not_guessed():
    import numpy as np

    from semservo.wire import Frame, frame_header

    stage = Port(move={"voltages": {}})
    core = core_with(stage=stage, controller=Port(status={"state": "idle"}))
    pixels = np.zeros((64, 64), np.uint8)
    core.latest = Frame(header=frame_header(pixels, seq=1, acquired_at_ns=1, source="watch"), pixels=pixels)
    with pytest.raises(GatewayError) as refused:
        core.center(10.0, 20.0)
    assert refused.value.status == 409 and refused.value.code == "pixel_size_unknown"
    assert stage.asked == []
