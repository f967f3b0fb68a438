"""Faults as containers meet them: a service's process dies (the restart policy brings
it back), the network between the two PCs is cut mid-run. Each run ends saying why,
nothing hangs, the stage holds, and the records say what happened."""

from __future__ import annotations

import json
import os
import signal
import time


def _wait_restarted(system, service: str, old_pid: int, restarts: int, timeout_s: float = 90.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        info = system.info(service)
        if info["running"] and info["pid"] not in (0, old_pid) and info["restarts"] > restarts:
            return info
        time.sleep(0.5)
    raise AssertionError(f"{service} was not restarted within {timeout_s:.0f} s: {system.info(service)}")


def test_the_stage_process_killed_mid_run(system, lab):
    """As a crash would: SIGKILL to the stage service's host pid."""
    run = system.displace_and_start(lab, offset=(8.0, -6.0), tolerance_px=0.01, max_iterations=500)
    system.wait_iterations(lab, run["run_id"], 2)
    before = system.info("stage")
    killed_at_ns = time.time_ns()
    os.kill(before["pid"], signal.SIGKILL)

    result = lab.wait(run["run_id"], timeout=60)
    assert result["state"] == "failed"
    assert "stage" in result["reason"], result["reason"]

    after = _wait_restarted(system, "stage", before["pid"], before["restarts"])
    assert after["restarts"] == before["restarts"] + 1
    assert system.stack.wait_healthy(120, services=("stage",))
    stage = lab.stage()
    # A run had it armed when it died: it comes back held, not free to move.
    assert stage["state"] == "held" and "restarted" in stage["reason"], stage

    # The command log is on the volume: the moves sent before the kill are still there,
    # after the restarted process's own start-up.
    lines = system.exec("stage", "cat", "/data/runs/stage-commands.jsonl").stdout.decode().splitlines()
    entries = [json.loads(line) for line in lines if line.strip()]
    moves_before = [e for e in entries if e["time_ns"] < killed_at_ns and e["text"].startswith("set,")]
    restarted = [e for e in entries if e["time_ns"] > killed_at_ns and e["text"] == "ver"]
    assert moves_before and restarted, entries[-20:]
    # The run's record carries that log too (asked of the stage once it was back).
    assert any(e["text"].startswith("set,") for e in lab.run(run["run_id"])["stage_commands"])


test_the_stage_process_killed_mid_run.restarts_expected = {"stage"}


def test_the_network_between_the_two_pcs_cut_mid_run(system, lab):
    """The image server (PC 1) loses the work network (PC 2): frames stop crossing."""
    work, imageserver = system.stack.network("work"), system.stack.container("imageserver")
    run = system.displace_and_start(lab, offset=(8.0, -6.0), tolerance_px=0.01, max_iterations=500)
    system.wait_iterations(lab, run["run_id"], 2)
    system.engine.run("network", "disconnect", work, imageserver)
    connected = False
    try:
        cut_at = time.monotonic()
        result = lab.wait(run["run_id"], timeout=60)
        # Within the controller's estimate timeout (5 s), plus a poll: nothing hangs.
        assert time.monotonic() - cut_at < 30
        assert result["state"] == "failed"
        assert "frames stopped" in result["reason"], result["reason"]

        # The stage holds: no move after the run ended, the voltages stay; no frame
        # reaches PC 2, and the gateway still answers.
        held, status = lab.stage()["voltages"], lab.status()
        time.sleep(2.0)
        assert lab.stage()["voltages"] == held
        assert lab.status()["latest_frame_seq"] == status["latest_frame_seq"]
        finished = result["finished_at_ns"]
        assert not [e for e in lab.run(run["run_id"])["stage_commands"]
                    if e["time_ns"] > finished and e["text"].startswith("set,")]

        system.engine.run("network", "connect", "--alias", "imageserver", work, imageserver)
        connected = True
        system.wait_frames(lab, after_seq=status["latest_frame_seq"])
        system.stack.wait_healthy(120)  # as an operator checks before the next run
        again = system.displace_and_start(lab, offset=(4.0, -3.0), tolerance_px=0.2)
        assert lab.wait(again["run_id"], timeout=240)["state"] == "converged"
    finally:
        if not connected:
            system.engine.run("network", "connect", "--alias", "imageserver", work, imageserver, check=False)
