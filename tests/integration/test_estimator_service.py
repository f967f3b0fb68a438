"""The estimator as a real process behind the image server, on the replayed 2013 run."""

from __future__ import annotations

import base64
import io
import json
import math
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from semservo.config import connect
from semservo.estimation import MotionEstimator
from semservo.messages import MOTION_TOPIC, Health, MotionEstimate
from semservo.transport import CommandError, ControlClient, MessageSubscriber
from tests.integration.helpers import start_service, stop, wait_healthy

pytestmark = pytest.mark.integration


@pytest.fixture
def stack(ports, recorded_run):
    imageserver = start_service("imageserver", "--source", "replay", "--glob", "frame*", "--fps", "20")
    wait_healthy(connect("127.0.0.1", ports["control"]), imageserver)
    estimator = start_service("estimator")
    control_endpoint = connect("127.0.0.1", ports["estimator_control"])
    wait_healthy(control_endpoint, estimator)
    control = ControlClient(control_endpoint, timeout_s=10, retries=1)
    motion = MessageSubscriber(connect("127.0.0.1", ports["motion"]), MOTION_TOPIC, MotionEstimate)
    yield control, motion, estimator
    control.close()
    motion.close()
    stop(estimator)
    stop(imageserver)


def wait_for_frame(control: ControlClient) -> None:
    import time

    deadline = time.monotonic() + 10
    while control.request("report")["latest_frame_seq"] is None:
        assert time.monotonic() < deadline, "the estimator never received a frame"
        time.sleep(0.05)


def estimates_for(motion: MessageSubscriber, reference_id: str, count: int) -> list[MotionEstimate]:
    found = []
    for _ in range(200):
        estimate = motion.receive(timeout_s=1)
        if estimate is not None and estimate.reference_id == reference_id:
            found.append(estimate)
            if len(found) == count:
                break
    return found


def png_b64(pixels: np.ndarray) -> str:
    buffer = io.BytesIO()
    Image.fromarray(pixels).save(buffer, format="PNG")
    return base64.b64encode(buffer.getvalue()).decode()


def test_without_a_reference_nothing_is_published_and_health_says_so(stack):
    control, motion, _ = stack
    wait_for_frame(control)
    health = Health.model_validate(control.request("health"))
    assert health.state == "idle"
    assert "none taught" in health.details["reference"]
    assert health.counters["frames_without_reference"] > 0
    assert motion.receive(timeout_s=0.5) is None


def test_teach_the_live_frame_then_motion_follows_each_frame(stack, recorded_run):
    control, motion, _ = stack
    wait_for_frame(control)
    reference = control.request("teach")
    assert reference["kind"] == "frame" and reference["shape"] == [512, 512]
    estimates = estimates_for(motion, reference["id"], 8)
    assert len(estimates) == 8
    seqs = [e.seq for e in estimates]
    assert seqs == sorted(seqs) and len(set(seqs)) == 8  # one per frame, newest first served
    taught_seq = reference["frame_seq"]
    frames = sorted(recorded_run.glob("frame*.png"))
    taught = np.asarray(Image.open(frames[taught_seq % len(frames)]))
    # Replayed at 20 frames/s: 50 ms apart, long enough for the scan-averaged shift
    # (the service's default; the recording does not say how long its scans took).
    assert all(estimate.scan_averaged for estimate in estimates[1:])
    for estimate in estimates[:3]:
        current = np.asarray(Image.open(frames[estimate.seq % len(frames)]))
        expected = MotionEstimator(taught, scan_averaged=estimate.scan_averaged).estimate(current)
        assert estimate.dx_px == pytest.approx(expected.dx, abs=1e-3)
        assert estimate.dy_px == pytest.approx(expected.dy, abs=1e-3)
        assert estimate.latency_ms >= estimate.estimation_ms > 0
        assert estimate.pixel_size_nm is None  # the recording does not say it: unknown, not made up
    health = Health.model_validate(control.request("health"))
    assert health.state == "running" and health.counters["motion_published"] >= 8


def test_teach_an_uploaded_image_and_the_real_run_converges(stack, recorded_run):
    control, motion, _ = stack
    wait_for_frame(control)
    reference = control.request("teach", image_b64=png_b64(np.asarray(Image.open(recorded_run / "reference.png"))))
    assert reference["kind"] == "image"
    estimates = estimates_for(motion, reference["id"], 10)
    early = [e for e in estimates if e.seq % 54 < 5]
    late = [e for e in estimates if e.seq % 54 > 45]
    for estimate in estimates:
        assert estimate.confidence > 0.5
    # The recorded run starts ~54 px left and ~41 px below the reference and ends near it.
    for estimate in early:
        assert estimate.dx_px < -30 and estimate.dy_px > 20
    for estimate in late:
        assert np.hypot(estimate.dx_px, estimate.dy_px) < 15


def test_teach_a_polygon_mask(stack):
    control, motion, _ = stack
    wait_for_frame(control)
    polygon = [[70, 140], [130, 120], [160, 300], [230, 300], [290, 140], [320, 160], [300, 430], [100, 440]]
    reference = control.request("teach", polygon=polygon)
    assert reference["kind"] == "mask" and reference["polygon"] == polygon
    estimates = estimates_for(motion, reference["id"], 3)
    assert len(estimates) == 3 and all(e.rotation_deg == 0 for e in estimates)


def test_bad_teach_requests_are_refused_and_keep_the_previous_reference(stack):
    control, _, estimator = stack
    wait_for_frame(control)
    good = control.request("teach")
    bad_requests = [
        ({"image_b64": "not base64!"}, "base64"),
        ({"image_b64": base64.b64encode(b"garbage bytes").decode()}, "unreadable"),
        ({"image_b64": png_b64(np.zeros((100, 80), np.uint8))}, "80 x 100"),
        ({"polygon": [[1, 2], [3, 4]]}, "at least 3"),
        ({"polygon": "nonsense"}, "polygon"),
        ({"path": "/nonexistent/frame.png"}, "unreadable"),
        ({"frames": 0}, "frames: Input should be greater than or equal to 1"),
        ({"frames": "four"}, "frames: Input should be a valid integer"),
        ({"frames": 17}, "frames: Input should be less than or equal to 16"),
    ]
    for args, message in bad_requests:
        with pytest.raises(CommandError, match=message) as caught:
            control.request("teach", **args)
        assert caught.value.code == "bad_request"
    assert control.request("report")["reference"]["id"] == good["id"]
    assert estimator.poll() is None


def test_clear_stops_the_motion_stream(stack):
    control, motion, _ = stack
    wait_for_frame(control)
    reference = control.request("teach")
    assert estimates_for(motion, reference["id"], 2)
    assert control.request("clear") == {"cleared": True}
    in_flight = 0
    while motion.receive(timeout_s=0.3) is not None:  # drain what was in flight
        in_flight += 1
    assert in_flight <= 8  # at most a queue's worth was on its way
    assert motion.receive(timeout_s=0.5) is None
    assert Health.model_validate(control.request("health")).state == "idle"


def test_estimate_cli_prints_each_readable_image_then_reports_the_rest(recorded_run, tmp_path):
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"not an image")
    command = [sys.executable, "-m", "semservo", "estimate", str(recorded_run / "reference.png"),
               str(recorded_run / "frame00.png"), str(broken), str(recorded_run / "frame53.png")]
    result = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert result.returncode == 1
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 2 and "frame00.png" in lines[0] and "frame53.png" in lines[1]
    for key in ("dx_px=", "dy_px=", "rotation_deg=", "confidence=", "snr_db=", "elapsed_ms="):
        assert key in lines[0]
    assert "broken.png" in result.stderr and "unreadable" in result.stderr

    result = subprocess.run(command[:6] + ["--json", "--no-rotation"], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0
    record = json.loads(result.stdout)
    assert set(record) == {"image", "dx_px", "dy_px", "rotation_deg", "confidence", "snr_db", "elapsed_ms"}
    assert record["dx_px"] == pytest.approx(-53.7, abs=1) and record["dy_px"] == pytest.approx(40.8, abs=1)
    assert record["rotation_deg"] == 0


def test_estimate_compares_a_pair_whose_data_bar_was_cut_from_one_file_only(sem_images):
    """The README's own example pair (696 x 520 and 696 x 515: five blank rows cut from one
    only) was refused; the common region is compared, and said so. --crop none refuses."""
    pair = [str(sem_images / "drift_pair_before.tif"), str(sem_images / "drift_pair_after.tif")]
    done = subprocess.run([sys.executable, "-m", "semservo", "estimate", "--json", *pair], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "comparing the common 696 x 515" in done.stderr
    motion = json.loads(done.stdout.splitlines()[0])
    assert (round(motion["dx_px"]), round(motion["dy_px"])) == (3, -5), motion  # the real drift, whole pixels
    refused = subprocess.run([sys.executable, "-m", "semservo", "estimate", "--crop", "none", *pair],
                             capture_output=True, text=True, timeout=120)
    assert refused.returncode == 1 and "696 x 515, the reference is 696 x 520" in refused.stderr


def test_estimate_refuses_a_flat_image_and_bad_options_and_its_json_stays_json(recorded_run, tmp_path):
    """A flat current image is refused as a flat reference is (it gave invented numbers);
    --polygon takes finite corner points; --json writes null, never -Infinity, for a
    frame whose SNR is not finite (a frame of pure noise)."""

    flat = tmp_path / "grey.png"
    Image.fromarray(np.full((512, 512), 128, np.uint8)).save(flat)
    reference = str(recorded_run / "reference.png")
    done = subprocess.run([sys.executable, "-m", "semservo", "estimate", "--json", reference, str(flat),
                           str(recorded_run / "frame00.png")], capture_output=True, text=True, timeout=120)
    assert done.returncode == 1
    assert "grey.png: the image is flat (every pixel 128): nothing to register" in done.stderr
    assert [json.loads(line)["image"] for line in done.stdout.splitlines()] == [str(recorded_run / "frame00.png")]
    done = subprocess.run([sys.executable, "-m", "semservo", "estimate", reference, str(flat), "--polygon",
                           "nan,0 10,0 10,10"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "argument --polygon: at least three corner points" in done.stderr
    done = subprocess.run([sys.executable, "-m", "semservo", "estimate", "--mask", reference,
                           str(recorded_run / "frame00.png")], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "reference.png (the mask) is not binary" in done.stderr, done.stderr
    noise = tmp_path / "noise.png"
    Image.fromarray(np.random.default_rng(0).integers(0, 256, (512, 512), dtype=np.uint8)).save(noise)
    done = subprocess.run([sys.executable, "-m", "semservo", "estimate", "--json", reference, str(noise)],
                          capture_output=True, text=True, timeout=120)
    assert "Infinity" not in done.stdout and "NaN" not in done.stdout
    record = json.loads(done.stdout)
    assert record["snr_db"] is None or math.isfinite(record["snr_db"])


def test_teach_and_watch_commands_refuse_what_they_cannot_use(tmp_path):
    """`semservo teach --image` on no file or a folder says so (it was a traceback), before
    asking any service; `frames` and `motion` take a count of 1 or more."""
    for path, says in ((tmp_path / "nope.png", "no such image file"), (tmp_path, "a folder, not an image file")):
        done = subprocess.run([sys.executable, "-m", "semservo", "teach", "--image", str(path)], capture_output=True,
                              text=True, timeout=60)
        assert done.returncode == 2 and says in done.stderr and "Traceback" not in done.stderr
    for command in ("frames", "motion"):
        done = subprocess.run([sys.executable, "-m", "semservo", command, "--count", "0"], capture_output=True,
                              text=True, timeout=60)
        assert done.returncode == 2 and "argument --count: must be 1 or more, got 0" in done.stderr
