"""`./dev compose down` then `./dev compose up`: new containers (new keys, new token, a
new simulated world), the same records volume. Every run record and the stage's state
survive on it."""

from __future__ import annotations

import json
import time


def test_down_then_up_keeps_every_run_and_the_stage_state(system):
    with system.client() as lab:
        # A run of its own, stopped by the operator: the stage stops first, then the run.
        run = system.displace_and_start(lab, offset=(3.0, -2.0), tolerance_px=0.01, max_iterations=500)
        lab.stop("operator stop before down")
        assert lab.wait(run["run_id"], timeout=60)["state"] == "stopped"
        before = {record["id"]: record["state"] for record in lab.runs(limit=1000)}
        stage = lab.stage()
        assert run["run_id"] in before and stage["state"] == "stopped", (before, stage)
    ids_before = {service: info["id"] for service, info in system.stack.containers().items()}
    down_at_ns = time.time_ns()

    system.dev_compose("down")
    assert not system.stack.containers()
    system.dev_compose("up")

    ids_after = {service: info["id"] for service, info in system.stack.containers().items()}
    assert set(ids_after) == set(ids_before) and not set(ids_after.values()) & set(ids_before.values())
    with system.client() as lab:
        assert {record["id"]: record["state"] for record in lab.runs(limit=1000)} == before
        assert lab.run(run["run_id"])["reason"] == "operator stop before down"
        stage = lab.stage()
        # Stopped by an operator before the restart: still stopped until someone resumes.
        assert stage["state"] == "stopped" and "before a restart" in stage["reason"], stage
    # And the stage's command log: what it sent before the down is still on the volume.
    log = system.exec("stage", "cat", "/data/runs/stage-commands.jsonl").stdout.decode().splitlines()
    assert any(json.loads(line)["time_ns"] < down_at_ns and json.loads(line)["text"].startswith("set,")
               for line in log if line.strip())
