"""Five degrees of freedom through the REST API on the simulated lab: x, y, the rotation
about the beam (gamma) and the two tilts (alpha, beta), the tilts measured from focus
sweeps by the estimator through the image server, every axis moved by the stage
service. The simulated lab runs the small-depth-of-field ``tilts`` preset."""

from __future__ import annotations

import time

import pytest

from semservo.client import Client, SemservoError
from tests.conftest import simulated_stack
from tests.integration.helpers import wait_for

pytestmark = pytest.mark.integration

SPEEDUP = 20


@pytest.fixture(scope="module")
def system(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tilts")
    with simulated_stack(folder, speedup=SPEEDUP, SEMSERVO_FAKELAB__PRESET="tilts") as (launcher, settings):
        client = Client(f"http://127.0.0.1:{settings.gateway.http_port}", timeout=30)
        try:
            wait_for(lambda: client.status()["latest_frame_seq"] is not None, 60, "frames at the gateway")
            yield {"client": client, "settings": settings}
        finally:
            client.close()


def test_a_tilt_run_needs_a_taught_sweep_and_says_so(system):
    lab = system["client"]
    lab.teach(frames=2)
    with pytest.raises(SemservoError) as refusal:
        lab.start(dofs=["x", "y", "alpha", "beta"])
    # 409: the request is well formed, the system lacks a taught sweep (schemathesis
    # counts a 422 for a schema-valid body as a wrong answer).
    assert refusal.value.status == 409 and "teach with tilts=true" in refusal.value.message
    with pytest.raises(SemservoError) as refusal:
        lab.start(dofs=["x", "y", "pitch"])
    assert refusal.value.status == 422
    # A tilt beyond the stage's travel: refused, said, and nothing moves.
    before = lab.stage()["rotation"]["angles_deg"]
    with pytest.raises(SemservoError) as refusal:
        lab.rotate(tilt_x_deg=60.0, relative=False)
    assert refusal.value.status == 422 and refusal.value.field == "tilt_x_deg"
    lab.rotate(tilt_y_deg=20.0)
    with pytest.raises(SemservoError) as refusal:
        lab.rotate(tilt_y_deg=28.0)  # to 48 degrees: beyond the +-45 of travel
    assert refusal.value.status == 409 and refusal.value.code == "rotation_limit"
    back = lab.rotate(tilt_y_deg=-20.0)
    assert back["targets_deg"]["tilt_y_deg"] == pytest.approx(before["tilt_y_deg"])
    time.sleep(1.0)  # 20 degrees at 4 degrees per simulated second, the lab 20 times faster


def test_a_teach_with_tilts_answers_at_once_and_reports_its_sweeps_progress(system):
    """The sweep takes seconds of scans: the teach answers with a handle (the reference,
    its sweep ``sweeping``), the progress is read from GET /reference, and a run started
    before it is done is refused saying so."""
    lab = system["client"]
    asked = time.monotonic()
    reference = lab.teach(frames=2, tilts=True, wait=False)
    assert time.monotonic() - asked < 5.0
    assert reference.tilt_teach is not None and reference.tilt_teach.state == "sweeping"
    assert reference.tilt_teach.focus_measure == "normalized_variance"  # the default: eq. 13
    with pytest.raises(SemservoError) as refused:
        lab.start(dofs=["alpha", "beta"])
    assert refused.value.status == 409 and "still scanning" in refused.value.message
    assert refused.value.code == "no_tilt_reference"
    seen = set()
    done = wait_for(lambda: (now := lab.reference()).tilt_teach.state != "sweeping" and now or
                    seen.add(now.tilt_teach.scanned), 120, "the taught pose's sweep")
    assert done.tilt_teach.state == "done" and done.tilt["frames"] == done.tilt_teach.frames >= 7
    assert len(seen) >= 2, "the scans were counted as they came"
    # Every sweep was steadied: the lab drifts while it scans, and the estimator moved each
    # frame back by how far the live frames between them had seen the content move.
    moved = done.tilt["content_moved_px"]
    assert len(moved) == done.tilt["sweeps"] and all(isinstance(each, float) and each > 0 for each in moved), moved


def test_servoes_all_five_degrees_of_freedom_through_the_api(system):
    lab = system["client"]
    reference = lab.teach(frames=2, tilts=True)
    assert reference["tilt"]["kernels_used"] >= 20 and reference["tilt"]["frames"] >= 7
    lab.move(x_um=2.0, y_um=-1.5)
    lab.rotate(rotation_deg=3.0, tilt_x_deg=2.0, tilt_y_deg=-1.5)
    run = lab.start(dofs=["x", "y", "gamma", "alpha", "beta"], tolerance_px=0.3, tolerance_deg=0.05,
                    tolerance_tilt_deg=0.15, max_iterations=400)
    record = lab.wait(run["run_id"], timeout=400)
    assert record["state"] == "converged", record["reason"]
    records = record["trajectory"]
    tilt_moves = [r for r in records if r.get("tilt_action") == "moved"]
    assert tilt_moves, "the tilts were servoed"
    # Each tilt move restarted the estimator's sweeps (the one scanning was cancelled).
    assert all(r.get("tilt_sweeps_restarted") for r in tilt_moves)
    assert any("angles_deg" in r for r in records)
    truth = record["truth"]
    print("5-DOF run:", record["iterations"], "iterations, truth", truth)
    # The stage's x, y against the taught ones: the view matches, but a residual tilt of
    # 0.1 degree about the pivot 20 um below the surface moves the view by 0.5 px, which
    # the stage's x, y then make up for.
    assert truth["error_norm_px"] < 2.0
    assert abs(truth["error_deg"]["rotation_deg"]) < 0.1
    assert abs(truth["error_deg"]["tilt_x_deg"]) < 0.3 and abs(truth["error_deg"]["tilt_y_deg"]) < 0.3
    # The record and the CSV carry the tilts of every iteration with a sweep.
    table = lab.http.get(f"/runs/{run['run_id']}.csv").text.splitlines()
    assert "alpha_deg" in table[0] and "beta_deg" in table[0]


def test_the_image_server_focuses_and_sweeps_on_command(system):
    from semservo.config import connect
    from semservo.transport import CommandError, ControlClient
    from services.imageserver.sweep import decode_sweep

    settings = system["settings"]
    control = ControlClient(connect("127.0.0.1", settings.imageserver.control_port), timeout_s=10, retries=1)
    try:
        assert control.request("set_scan", working_distance_um=2.0)["working_distance_um"] == 2.0
        assert control.request("set_scan", working_distance_um=0.0)["working_distance_um"] == 0.0
        for bad in ([0.0, 1.0], [0.0, 2.0, 1.0], [0.0, float("inf"), 1.0]):
            with pytest.raises(CommandError):
                control.request("start_sweep", working_distances_um=bad)
        def start():
            try:  # the estimator's last sweep of the run before may still be scanning: busy, said so
                return control.request("start_sweep", working_distances_um=[-7.0, 0.0, 7.0])
            except CommandError as error:
                assert error.code == "busy", error
                return None

        started = wait_for(start, 60, "the image server free to sweep")
        result = wait_for(lambda: (r := control.request("sweep", sweep_id=started["sweep_id"]))["state"] != "scanning"
                          and r, 60, "the focus sweep")
        assert result["state"] == "done" and result["pixel_size_nm"] > 0
        frames = decode_sweep(result).astype(float)
        assert frames.shape == (3, 512, 512)
        # In focus in the middle of the sweep: the sharpest frame (the largest normalized variance).
        sharpness = [frame.var() / frame.mean() for frame in frames]
        assert sharpness[1] > max(sharpness[0], sharpness[2])
    finally:
        control.close()
