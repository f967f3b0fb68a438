"""The whole system behind its REST API: the real stack started by the launcher on
simulated hardware (fake lab sped up, image server, estimator, stage on the emulated
NV 40/3, controller, gateway on uvicorn), driven through `semservo.client` only.

One stack serves the module (starting it takes ~10 s); the tests that kill or restart
a service come last.
"""

from __future__ import annotations

import io
import os
import signal

import numpy as np
import pytest
from PIL import Image

from semservo.client import Client, RunActive, SemservoError
from tests.conftest import simulated_stack
from tests.integration.helpers import wait_for

pytestmark = pytest.mark.integration

SPEEDUP = 20


@pytest.fixture(scope="module")
def system(tmp_path_factory):
    folder = tmp_path_factory.mktemp("gateway")
    with simulated_stack(folder, speedup=SPEEDUP, SEMSERVO_GATEWAY__MAX_UPLOAD_BYTES=str(2 * 2**20),
                         SEMSERVO_GATEWAY__SAVE_FRAMES="true") as (launcher, settings):
        client = Client(f"http://127.0.0.1:{settings.gateway.http_port}", timeout=15)
        try:
            yield {"client": client, "launcher": launcher, "settings": settings, "folder": folder}
        finally:
            client.close()


def frames_flowing(lab: Client) -> None:
    wait_for(lambda: lab.status()["latest_frame_seq"] is not None, 30, "frames at the gateway")


def settle(lab: Client, frames: int = 3) -> None:
    seq = lab.status()["latest_frame_seq"]
    wait_for(lambda: lab.status()["latest_frame_seq"] >= seq + frames, 30, "new frames")


def png(pixels: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(pixels).save(buffer, format="PNG")
    return buffer.getvalue()


def test_teach_jog_position_and_the_record(system):
    lab = system["client"]
    frames_flowing(lab)
    reference = lab.teach(frames=4)
    assert reference["kind"] == "frame" and reference["thumbnail_url"] == "/reference.png"
    lab.move(x_um=5.0, y_um=-3.5)  # the operator's joystick
    settle(lab)
    moved = lab.status()
    assert moved["stage"]["link"] == "connected"

    run = lab.start(tolerance_px=0.1)
    result = lab.wait(run["run_id"], timeout=120)
    assert result["state"] == "converged", result["reason"]
    assert result["iterations"] >= 2
    # The truth from the simulator: where the run ended against where it was taught
    # (from a 33 px jog back to within half a pixel; the benchmark measures the spread).
    truth = result["truth"]
    assert truth is not None and truth["error_norm_px"] < 0.5, truth
    assert result["final_error_px"] <= 0.1  # as the controller judged it: the law's estimate
    assert any(r["action"] == "moved" for r in result["trajectory"])
    assert result["stage_commands"], "the stage command log is kept with the run"
    assert result["settings"]["tolerance_px"] == 0.1
    # The reference's acquisition, as its frames said it, is kept with the run.
    acquisition = result["reference"]["acquisition"]
    assert acquisition["pixel_size_nm"] == pytest.approx(result["trajectory"][-1]["pixel_size_nm"])
    assert acquisition["magnification"] > 0 and acquisition["dwell_ns"] > 0

    # The same run in the history, as CSV and as a Fig. 9 report.
    assert any(summary["id"] == run["run_id"] and summary["state"] == "converged" for summary in lab.runs())
    table = lab.http.get(f"/runs/{run['run_id']}.csv")
    assert table.status_code == 200 and table.text.splitlines()[0].startswith("iteration,seq,action")
    assert len(table.text.splitlines()) == 1 + len(result["trajectory"])
    report = lab.http.get(f"/runs/{run['run_id']}/report.png")
    assert report.headers["content-type"] == "image/png"
    assert Image.open(io.BytesIO(report.content)).size == (1000, 320)

    # The run's frames, kept as TIFF with their metadata.
    from semservo.imagefiles import read_image

    saved = sorted((system["folder"] / "runs" / "frames" / run["run_id"]).glob("*.tif"))
    assert len(saved) >= result["iterations"]
    pixels, metadata = read_image(saved[-1])
    assert pixels.shape == (512, 512) and metadata["pixel_size_nm"] == pytest.approx(result["trajectory"][-1]
                                                                                     ["pixel_size_nm"])


def test_images_metrics_and_events(system):
    lab = system["client"]
    frames_flowing(lab)
    lab.teach()
    for path in ("/frames/latest.png", "/reference.png", "/difference.png"):
        response = lab.http.get(path)
        assert response.status_code == 200, path
        image = Image.open(io.BytesIO(response.content))
        assert image.size == (512, 512) and image.mode == "L"
    metrics = lab.http.get("/metrics").text
    assert 'semservo_service_up{service="estimator"} 1.0' in metrics
    assert "semservo_frames_total" in metrics

    # WS /events: the per-iteration records of a run arrive live.
    lab.move(x_um=3.0, y_um=2.0)
    received = []
    stream = lab.events()
    assert next(stream)["kind"] == "hello"
    run = lab.start()
    for event in stream:
        received.append(event)
        if event["kind"] == "status" and event["data"]["state"] in ("converged", "failed", "stopped"):
            break
    stream.close()
    # With quiet_s, a quiet stream yields None, so a loop can look at its clock.
    quiet = lab.events(quiet_s=0.3)
    assert next(quiet)["kind"] == "hello"
    assert any(next(quiet) is None for _ in range(20)), "after the run, the stream falls quiet"
    quiet.close()
    iterations = [e for e in received if e["kind"] == "iteration"]
    assert iterations and all(e["run_id"] == run["run_id"] for e in iterations)
    assert any(e["data"].get("action") == "moved" for e in iterations)
    lab.wait(run["run_id"], timeout=60)


def test_stop_midway_and_a_second_start_is_409(system):
    lab = system["client"]
    frames_flowing(lab)
    lab.teach()
    lab.move(x_um=9.0, y_um=7.0)
    settle(lab)
    run = lab.start(tolerance_px=0.01, max_iterations=10_000)
    with pytest.raises(RunActive) as second:
        lab.start()
    assert second.value.status == 409 and second.value.run_id == run["run_id"]
    wait_for(lambda: lab.status()["iteration"] >= 1, 60, "the first iteration")
    stopped = lab.stop("test stops midway")
    assert stopped["state"] == "stopped" and stopped["stage_stopped"]
    record = lab.wait(run["run_id"], timeout=30)
    assert record["state"] == "stopped" and "midway" in record["reason"]
    assert lab.stage()["state"] == "stopped"
    with pytest.raises(SemservoError) as refused:
        lab.move(x_um=0.5)
    assert refused.value.status == 409 and refused.value.code == "stopped"
    # A start does not silently resume a stopped stage: the operator says so.
    with pytest.raises(SemservoError) as refused:
        lab.start(tolerance_px=0.2)
    assert refused.value.status == 409 and refused.value.code == "stage_stopped"
    assert lab.stage()["state"] == "stopped"
    again = lab.start(tolerance_px=0.2, resume=True)
    assert lab.wait(again["run_id"], timeout=120)["state"] == "converged"


@pytest.mark.parametrize("body, field", [
    ({"tolerance_px": -1}, "tolerance_px"),
    ({"tolerance_px": "small"}, "tolerance_px"),
    ({"dofs": ["z"]}, "dofs.0"),
    ({"max_iterations": 0}, "max_iterations"),
    ({"warp_speed": True}, "warp_speed"),
])
def test_a_bad_start_body_is_a_422_naming_the_field(system, body, field):
    response = system["client"].http.post("/start", json=body)
    assert response.status_code == 422
    error = response.json()["error"]
    assert error["field"] == field and error["message"]


@pytest.mark.parametrize("body, field", [
    ({"x_um": "left"}, "x_um"),
    ({"x_um": 1e5}, "x_um"),
    ({}, "x_um"),
    ({"x_um": 1, "teleport": True}, "teleport"),
])
def test_a_bad_move_body_is_a_422_naming_the_field(system, body, field):
    response = system["client"].http.post("/stage/move", json=body)
    assert response.status_code == 422 and response.json()["error"]["field"] == field


def test_a_move_outside_the_limits_is_refused_with_the_rule(system):
    lab = system["client"]
    with pytest.raises(SemservoError) as refused:
        lab.move(x_um=-5.0, relative=False)
    assert refused.value.status == 409 and refused.value.code == "travel_limit"
    with pytest.raises(SemservoError) as refused:
        lab.move(x_um=40.0)
    assert refused.value.status == 409 and refused.value.code == "step_limit"
    with pytest.raises(SemservoError) as refused:  # past +-100: the stage's travel rule, not a fixed 422
        lab.move(x_um=500.0, relative=False)
    assert refused.value.status == 409 and refused.value.code == "travel_limit"


def test_bad_uploads_are_refused_and_keep_the_previous_reference(system):
    lab = system["client"]
    frames_flowing(lab)
    frame = np.array(Image.open(io.BytesIO(lab.http.get("/frames/latest.png").content)))
    good = lab.teach()
    cases = [
        ({"image": ("frame.png", b"not an image at all")}, 422, "unreadable_image"),
        ({"image": ("small.png", png(np.zeros((100, 80), np.uint8)))}, 422, "wrong_size"),
        ({"mask": ("mask.png", png(np.zeros((64, 64), np.uint8)))}, 422, "wrong_size"),
        ({"image": ("huge.png", b"\0" * (2 * 2**20 + 10))}, 413, "too_large"),
        ({"image": ("empty.png", b"")}, 422, "empty"),
    ]
    for files, status, code in cases:
        response = lab.http.post("/teach", files=files)
        assert response.status_code == status, (code, response.text)
        assert response.json()["error"]["code"] == code
        assert "BytesIO" not in response.text  # the upload named as such, not by its buffer's repr
    # A query's NaN reads as what it is, not as out of range; a body that is not JSON names no field.
    response = lab.http.post("/teach", params={"dwell_ns": "NaN"})
    assert response.status_code == 422 and response.json()["error"]["message"].startswith("NaN is not a finite number")
    response = lab.http.post("/start", content=b"{not json", headers={"content-type": "application/json"})
    refused = response.json()["error"]
    assert response.status_code == 422 and refused["field"] is None and "not valid JSON" in refused["message"]
    response = lab.http.post("/teach/polygon", json={"polygon": [[1, 2], [3, 4]]})
    assert response.status_code == 422 and response.json()["error"]["field"] == "polygon"
    response = lab.http.post("/teach", params={"frames": 99})
    assert response.status_code == 422 and response.json()["error"]["field"] == "frames"
    # A misspelt part or parameter would have taught the live frame in place of the upload.
    response = lab.http.post("/teach", files={"imag": ("frame.png", png(np.zeros((512, 512), np.uint8)))})
    refused = response.json()["error"]
    assert response.status_code == 422 and refused["field"] == "imag" and "does not take 'imag'" in refused["message"]
    response = lab.http.post("/teach", params={"frame": 4})
    assert response.status_code == 422 and response.json()["error"]["field"] == "frame"
    # A picture given as a mask is not two levels: refused, not read as "every pixel above 0".
    response = lab.http.post("/teach", files={"mask": ("frame.png", png(frame))})
    assert response.status_code == 422 and "is not binary" in response.json()["error"]["message"]
    assert lab.status()["reference"]["id"] == good["id"]


def test_teach_a_slow_high_quality_scan(system):
    lab = system["client"]
    frames_flowing(lab)
    slow = lab.teach(dwell_ns=2900)  # paper case 5: one slow scan as the reference
    assert slow["kind"] == "image" and "2900 ns/px" in slow["detail"]["label"]
    assert lab.status()["reference"]["id"] == slow["id"]
    response = lab.http.post("/teach", params={"dwell_ns": -5})
    assert response.status_code == 422 and response.json()["error"]["field"] == "dwell_ns"


def test_teach_from_an_upload_and_a_clicked_polygon(system):
    lab = system["client"]
    frames_flowing(lab)
    frame = np.array(Image.open(io.BytesIO(lab.http.get("/frames/latest.png").content)))
    uploaded = lab.teach(image=png(frame), label="from the dashboard")
    assert uploaded["kind"] == "image"
    mask = lab.teach(polygon=[[150, 150], [350, 160], [340, 360], [160, 350]])
    assert mask["kind"] == "mask" and lab.status()["reference"]["id"] == mask["id"]


@pytest.mark.parametrize("script, args, expect", [
    ("position_to_target.py", [], r"converged after \d+ iterations"),
    ("visit_targets.py", [], r"target-0: converged in \d+ iterations"),
    ("hold_against_drift.py", ["3"], r"held for 3 s; largest error seen [\d.]+ px"),
])
def test_the_examples_run(system, script, args, expect, tmp_path):
    import re
    import subprocess
    import sys
    from pathlib import Path

    env = {**os.environ, "SEMSERVO_URL": str(system["client"].http.base_url).rstrip("/")}
    done = subprocess.run([sys.executable, str(Path(__file__).parents[2] / "examples" / script), *args], env=env,
                          cwd=tmp_path, capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stdout + done.stderr
    assert re.search(expect, done.stdout), done.stdout


def test_the_hold_example_ends_with_its_run_and_leaves_an_operators_stop_alone(system, tmp_path):
    """examples/hold_against_drift.py once waited forever when its run ended early (it
    looked at the clock only when an event came, and none come after a run ends), and it
    ended with a resume that would have undone the operator's stop."""
    import subprocess
    import sys
    from pathlib import Path

    lab = system["client"]
    frames_flowing(lab)
    env = {**os.environ, "SEMSERVO_URL": str(lab.http.base_url).rstrip("/")}
    script = Path(__file__).parents[2] / "examples" / "hold_against_drift.py"
    process = subprocess.Popen([sys.executable, str(script), "600"], env=env, cwd=tmp_path, text=True,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        wait_for(lambda: lab.status()["state"] == "servoing", 60, "the example's run")
        lab.stop("operator emergency")
        out, _ = process.communicate(timeout=60)
        assert process.returncode == 1, out
        assert "before the hold was over (stopped: operator emergency)" in out, out
        assert lab.stage().state == "stopped", "the operator's stop stands"
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        lab.resume()  # the next test's stage may move


def test_a_teach_right_after_a_jog_averages_only_frames_scanned_after_it(system):
    """examples/visit_targets.py once taught two of its targets from frames scanned while
    the stage was still moving: the reference was a blend of two views, and the runs to
    them 'converged' 8-15 px from where the stage had been. The teach now waits for
    frames scanned after the stage's last move settled."""
    lab = system["client"]
    frames_flowing(lab)
    seq = lab.status()["latest_frame_seq"]
    lab.move(x_um=8.0, y_um=0.0)
    settled_at_ns = lab.stage().settled_at_ns
    # As the example did: two frames on (the first of them was being scanned during the move).
    wait_for(lambda: lab.status()["latest_frame_seq"] >= seq + 2, 30, "two more frames")
    taught = lab.teach(frames=2)
    assert settled_at_ns > 0 and taught.detail["frames_averaged"] == 2
    run = lab.start(tolerance_px=0.1)
    result = lab.wait(run.run_id, timeout=120, stop_on_timeout=True)
    assert result.state == "converged", result.reason
    assert result.truth is not None and result.truth["error_norm_px"] < 0.3, result.truth


def test_a_demo_that_gives_up_stops_the_run_it_started(system, tmp_path):
    """`./dev demo` against a running system once gave up after its timeout and left its
    run servoing for hundreds of iterations."""
    import subprocess
    import sys

    lab = system["client"]
    done = subprocess.run([sys.executable, "-m", "semservo", "demo", "--url", str(lab.http.base_url).rstrip("/"),
                           "--timeout", "1", "--offset", "9", "-7", "--law", "paper"], cwd=tmp_path, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 1 and "demo gave up" in done.stderr and "it was stopped" in done.stderr, done.stderr
    run_id = lab.runs(limit=1)[0].id
    run = lab.wait(run_id, timeout=30)
    assert run.state == "stopped" and "gave up waiting" in run.reason
    assert lab.stage().state == "stopped", "a stop holds the stage, as every stop does"
    assert "--resume" in done.stderr, "the message says how the next demo gets past the stop"
    # A demo without --resume refuses before its teach: the taught reference stays.
    taught = lab.reference().id
    refused = subprocess.run([sys.executable, "-m", "semservo", "demo", "--url", str(lab.http.base_url).rstrip("/")],
                             cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert refused.returncode == 1 and "nothing was taught or moved" in refused.stderr, refused.stderr
    assert "this demo again with --resume" in refused.stderr and lab.reference().id == taught
    # The next demo, as the message says: it resumes the stage first (and gives up again).
    again = subprocess.run([sys.executable, "-m", "semservo", "demo", "--url", str(lab.http.base_url).rstrip("/"),
                            "--timeout", "1", "--offset", "-9", "7", "--law", "paper", "--resume"], cwd=tmp_path,
                           capture_output=True, text=True, timeout=120)
    assert "resumed (--resume)" in again.stdout and "demo gave up" in again.stderr, again.stdout + again.stderr
    lab.wait(lab.runs(limit=1)[0].id, timeout=30)
    lab.resume()


def test_the_client_covers_the_api_records_and_stored_targets(system, tmp_path):
    """A lab script needs no raw HTTP: resume, a run's CSV and report, stored targets
    saved, listed, exported, imported elsewhere and gone back to."""
    from semservo.client import save

    lab = system["client"]
    frames_flowing(lab)
    run_id = lab.runs(limit=1)[0].id
    csv = save(lab.run_csv(run_id), tmp_path / "run.csv").read_text().splitlines()
    assert csv[0].startswith("iteration,seq,action")
    assert lab.run_report(run_id)[:8] == b"\x89PNG\r\n\x1a\n"
    taught = lab.teach(frames=2)
    target = lab.save_target("bench corner", note="the left edge of the part", replace=True)
    assert target.reference["id"] == taught.id and target.stage["positions_um"]["x"] > 0
    assert "the left edge" in target.note and target.thumbnail_url == "/targets/bench%20corner/thumbnail.png"
    assert lab.http.get(target.thumbnail_url).headers["content-type"] == "image/png"
    with pytest.raises(SemservoError) as refused:
        lab.save_target("bench corner")
    assert refused.value.status == 409 and refused.value.code == "target_exists"
    exported = save(lab.export_target("bench corner"), tmp_path / "corner.tif")
    imported = lab.import_target(exported, name="corner copy")
    assert imported.reference == target.reference and imported.stage == target.stage
    assert {t.name for t in lab.targets()} >= {"bench corner", "corner copy"}
    lab.move(x_um=4.0, y_um=3.0)
    run = lab.go_to_target("corner copy", tolerance_px=0.15)  # days later: the stored pose, then the image
    result = lab.wait(run.run_id, timeout=120)
    assert result.state == "converged", result.reason
    assert lab.reference().target == "corner copy" and result.reference["id"] != taught.id
    assert result.truth is None or result.truth["error_norm_px"] < 0.6, "the stored target's truth goes with it"
    lab.delete_target("corner copy")
    with pytest.raises(SemservoError) as missing:
        lab.target("corner copy")
    assert missing.value.status == 404 and missing.value.code == "no_such_target"


def test_the_api_docs_are_served_without_internet(system):
    lab = system["client"]
    for page, asset in (("/docs", "/docs-assets/swagger-ui-bundle.js"), ("/redoc", "/docs-assets/redoc.standalone.js")):
        html = lab.http.get(page).text
        assert asset in html and "cdn" not in html.lower() and "googleapis" not in html, page
        assert lab.http.get(asset).status_code == 200


def test_a_reference_taught_elsewhere_is_the_one_everyone_shows(system):
    """`semservo teach` (the CLI, straight to the estimator) once left the gateway and the
    dashboard showing the previous reference."""
    import subprocess
    import sys

    lab = system["client"]
    frames_flowing(lab)
    before = lab.teach(frames=1)
    environment = {**os.environ}
    done = subprocess.run([sys.executable, "-m", "semservo", "teach", "--frames", "2"], env=environment,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    taught = done.stdout.split()[2]
    assert taught != before.id
    assert lab.status().reference.id == taught and lab.reference().id == taught
    assert lab.reference().detail["frames_averaged"] == 2


def test_async_client_reads_status_and_runs(system):
    import asyncio

    from semservo.client import AsyncClient

    async def read():
        async with AsyncClient(str(system["client"].http.base_url)) as lab:
            return await lab.status(), await lab.runs(limit=5)

    # In a thread of its own: a test session that also drives a browser (Playwright's
    # sync API) has an event loop running in the main thread.
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(1) as pool:
        status, runs = pool.submit(asyncio.run, read()).result(timeout=30)
    assert status["services"]["controller"]["up"] and status["latest_frame_seq"] is not None
    assert runs == system["client"].runs(limit=5)  # the same records as the sync client reads


def test_a_killed_service_is_named_down(system):
    lab, launcher = system["client"], system["launcher"]
    pid = launcher.health("estimator").pid
    os.kill(pid, signal.SIGKILL)
    status = wait_for(lambda: (s := lab.status())["down"] and s, 15, "the estimator reported down")
    assert status["down"] == ["estimator"]
    assert status["services"]["estimator"] == {"up": False, "state": "down", "last_error": status["services"]
                                               ["estimator"]["last_error"]}
    with pytest.raises(SemservoError) as refused:
        lab.teach()
    assert refused.value.status == 503 and refused.value.code == "estimator_unavailable"
    launcher.restart_service("estimator")
    assert wait_for(lambda: not lab.status()["down"], 15, "the estimator back")


def test_runs_survive_a_gateway_restart_and_a_run_it_missed_is_recorded(system):
    from semservo.config import connect
    from semservo.transport import ControlClient

    lab, launcher, settings = system["client"], system["launcher"], system["settings"]
    # A run the gateway records (whatever ran before this test).
    wait_for(lambda: _taught_or_none(lab), 30, "a teach (the estimator may have been restarted)")
    lab.http.post("/stage/resume")
    lab.move(x_um=2.0)
    lab.wait(lab.start(tolerance_px=0.2)["run_id"], timeout=90)
    before = lab.runs()
    stored = lab.save_target("before the restart", replace=True)
    # The gateway goes down; a run starts and ends without it (a script on the
    # controller's own socket).
    gateway = launcher.children["gateway"].process
    gateway.terminate()
    gateway.wait(timeout=15)
    stage = ControlClient(connect("127.0.0.1", settings.stage.control_port), timeout_s=5, retries=1)
    controller = ControlClient(connect("127.0.0.1", settings.controller.control_port), timeout_s=5, retries=1)
    try:
        stage.request("resume")
        stage.request("move", targets={"x": 2.0}, relative=True)
        missed = controller.request("start", tolerance_px=0.2)["run_id"]
        wait_for(lambda: controller.request("status")["state"] != "servoing", 90, "the missed run to end")
    finally:
        stage.close()
        controller.close()
    launcher.restart_service("gateway")
    # The first status completes the record of the run the gateway did not see.
    status = wait_for(lambda: _status_or_none(lab), 15, "the gateway back")
    assert status["run_id"] == missed
    after = lab.runs()
    assert after[0]["id"] == missed
    assert [run["id"] for run in after[1:]] == [run["id"] for run in before]
    record = lab.run(before[0]["id"])
    assert record["trajectory"] and record["state"] == before[0]["state"]
    recorded = lab.run(missed)
    assert recorded["state"] == "converged" and recorded["trajectory"] and recorded["stage_commands"]
    kept = lab.target("before the restart")  # stored targets survive a restart too
    assert kept == stored and lab.http.get(kept.thumbnail_url).status_code == 200


def _taught_or_none(lab: Client):
    try:
        return lab.teach()
    except SemservoError as error:
        assert "no frame" in error.message, error
        return None


def _status_or_none(lab: Client):
    try:
        return lab.status()
    except SemservoError:
        return None


def test_the_rotation_stage_turns_through_the_api_and_the_stage_rules(system):
    lab = system["client"]
    rotation = lab.stage()["rotation"]
    assert rotation["link"] == "connected" and rotation["travel_deg"]["tilt_x_deg"] == [-45.0, 45.0]
    before = rotation["angles_deg"]["rotation_deg"]
    turned = lab.rotate(rotation_deg=2.0)
    assert turned["targets_deg"]["rotation_deg"] == pytest.approx(before + 2.0)
    # It turns at its own speed; the stage's state follows it there (within the gear's play).
    wait_for(lambda: abs(lab.stage()["rotation"]["angles_deg"]["rotation_deg"] - (before + 2.0)) < 0.02, 10,
             "the rotation stage to arrive")
    for body in ({"rotation_deg": 400.0}, {"tilt_x_deg": 50.0}, {"relative": True}, {"rotation_deg": "1"},
                 {"rotation_deg": 1.0, "spin": 2.0}):
        response = lab.http.post("/stage/rotate", json=body)
        assert response.status_code == 422, (body, response.text)
    too_far = lab.http.post("/stage/rotate", json={"rotation_deg": 40.0})  # the stage's max_turn_deg is 30
    assert too_far.status_code == 409 and too_far.json()["error"]["code"] == "step_limit"
    lab.rotate(rotation_deg=before, relative=False)
    wait_for(lambda: abs(lab.stage()["rotation"]["angles_deg"]["rotation_deg"] - before) < 0.02, 10,
             "the rotation stage back")
