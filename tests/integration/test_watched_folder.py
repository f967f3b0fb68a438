"""Positioning from frames that arrive as files, as they do from an SEM whose software
saves each frame to a folder: the fake lab's SEM saves FEI-style TIFFs (with a data
bar and metadata) slowly, in chunks, into a folder; the image server's ``watch``
source follows it; the rest of the system is the usual one. Garbage dropped into the
folder mid-run is skipped, logged and counted, and the run goes on."""

from __future__ import annotations

import os

import pytest

from semservo.config import connect
from semservo.messages import Health
from semservo.transport import ControlClient
from tests.conftest import simulated_stack
from tests.integration.helpers import wait_for

pytestmark = pytest.mark.integration


def true_pose(fakelab: ControlClient, span_s: float = 0.5) -> tuple[float, float]:
    now = fakelab.request("pose")["t_s"]
    pose = fakelab.request("pose", interval_s=[now - span_s, now])
    return pose["x_um"], pose["y_um"]


def test_positions_the_stage_from_frames_saved_to_a_watched_folder(tmp_path):
    acquisition = tmp_path / "acquisition"
    acquisition.mkdir()
    with simulated_stack(tmp_path, SEMSERVO_IMAGESERVER__SOURCE="watch",
                         SEMSERVO_IMAGESERVER__WATCH_DIR=str(acquisition),
                         SEMSERVO_FAKELAB__SAVE_FRAMES_DIR=str(acquisition),
                         SEMSERVO_FAKELAB__SAVE_CHUNKS="6", SEMSERVO_FAKELAB__SAVE_CHUNK_PAUSE_S="0.01") \
            as (launcher, settings):
        def client(port: int) -> ControlClient:
            return ControlClient(connect("127.0.0.1", port), timeout_s=5, retries=1)

        estimator, stage = client(settings.estimator.control_port), client(settings.stage.control_port)
        controller, fakelab = client(settings.controller.control_port), client(settings.fakelab.control_port)
        imageserver = client(settings.imageserver.control_port)

        # Frames come from the files, with what the files say, and without their data bar.
        wait_for(lambda: estimator.request("report")["latest_frame_seq"] is not None, 60, "a frame from a file")
        info = imageserver.request("info")
        assert info["source"] == "watch" and info["files_published"] >= 1
        reference = estimator.request("teach")
        assert reference["shape"] == [512, 512]  # the 64-row data bar under each saved image is cropped
        assert reference["pixel_size_nm"] == pytest.approx(176.9167, rel=1e-4)  # from the file's FEI metadata
        taught = true_pose(fakelab)

        stage.request("move", targets={"x": 5.0, "y": -3.0}, relative=True)
        moved_at = fakelab.request("pose")["t_s"]
        # The pose averaged over half a simulated second that begins after the move settled
        # (wall time is no measure: the sped-up world stands still while it renders).
        wait_for(lambda: fakelab.request("pose")["t_s"] >= moved_at + 0.7, 30, "simulated time to pass the move")
        start = true_pose(fakelab)
        assert abs(start[0] - taught[0]) > 3 and abs(start[1] - taught[1]) > 2  # really displaced

        run = controller.request("start", tolerance_px=0.2)
        # Garbage lands in the folder mid-run, as on a shared drive: skipped, not fatal.
        (acquisition / "zz_garbage.tif").write_bytes(os.urandom(4000))
        (acquisition / "notes.txt").write_text("not a frame")
        status = wait_for(lambda: (s := controller.request("status"))["state"] != "servoing" and s, 120,
                          "the run to end")
        assert status["state"] == "converged", status
        record = controller.request("run")
        assert record["id"] == run["run_id"]
        fresh = [r for r in record["records"] if not r["action"].startswith("held")]
        assert fresh and all(r["pixel_size_nm"] == pytest.approx(176.9167, rel=1e-4) for r in fresh)
        # Frames scanned while the stage moved are recognised from the file's dwell and not acted on.
        assert any(r["action"].startswith("held: stale") for r in record["records"])

        final = true_pose(fakelab)
        pixel_um = 0.1769167
        error_px = [abs(final[axis] - taught[axis]) / pixel_um for axis in (0, 1)]
        print(f"converged in {record['iterations']} iterations; true final error {error_px} px")  # shown with -rP
        assert max(error_px) < 0.6, f"true final error {error_px} px"

        wait_for(lambda: Health.model_validate(imageserver.request("health")).counters.get("files_skipped", 0) >= 1,
                 15, "the garbage file to be skipped")
        health = Health.model_validate(imageserver.request("health"))
        assert health.counters["files_skipped"] == 1 and health.counters["files_published"] > 10
        assert health.state == "running"
        assert health.details["watch"]["mode"] == "inotify" and health.details["watch"]["since_last_frame_s"] < 5
        log = (tmp_path / "services.log").read_text()
        assert "skipped zz_garbage.tif: " in log
        for open_client in (estimator, stage, controller, fakelab, imageserver):
            open_client.close()
        state_dir = settings.stage.state_dir
        assert state_dir.is_dir() and state_dir.name.startswith("semservo-stage-")
    assert not state_dir.exists()  # the system's own stage-state folder goes with it
