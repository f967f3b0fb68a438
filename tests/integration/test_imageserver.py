"""The image server as a real process, replaying the real 2013 recording over ZeroMQ."""

from __future__ import annotations

import signal

import numpy as np
import pytest
from PIL import Image

from semservo.config import Settings, connect, pixel_size_nm
from semservo.messages import Health, Reply
from semservo.transport import CommandError, ControlClient, FrameSubscriber
from tests.integration.helpers import start_service, stop, wait_healthy

pytestmark = pytest.mark.integration


@pytest.fixture
def imageserver(ports, recorded_run):
    process = start_service("imageserver", "--source", "replay", "--fps", "40", "--magnification", "1200",
                            "--dwell-ns", "360")
    control = connect("127.0.0.1", ports["control"])
    wait_healthy(control, process)
    yield process, control
    stop(process)


def test_real_frames_arrive_with_correct_header_and_pixels(imageserver, ports, recorded_run):
    subscriber = FrameSubscriber(
        connect("127.0.0.1", ports["frames"]), max_message_bytes=Settings().max_message_bytes, latest_only=False
    )
    frames = [subscriber.receive(timeout_s=5) for _ in range(30)]
    subscriber.close()
    assert all(frame is not None for frame in frames)
    seqs = [frame.header.seq for frame in frames]
    assert seqs == list(range(seqs[0], seqs[0] + 30))  # consecutive, none lost
    for frame in frames:
        header = frame.header
        assert header.v == 1 and header.source == "replay"
        assert header.shape == (512, 512) and header.dtype == "uint8"
        assert header.magnification == 1200 and header.dwell_ns == 360
        assert header.pixel_size_nm == pytest.approx(pixel_size_nm(1200))
        assert header.acquired_at_ns <= header.published_at_ns
        expected = np.asarray(Image.open(recorded_run / header.label))
        np.testing.assert_array_equal(frame.pixels, expected)
    # name order: sequence n shows file n of the folder (its 54 frames, looping; not the
    # taught image beside them, reference.png)
    names = sorted(p.name for p in recorded_run.glob("frame*.png"))
    assert all(frame.header.label == names[frame.header.seq % len(names)] for frame in frames)


def test_control_socket_answers_and_survives_malformed_requests(imageserver):
    process, control = imageserver
    client = ControlClient(control, timeout_s=1)
    info = client.request("info")
    assert info["source"] == "replay" and info["frames"] == 54 and info["fps"] == 40
    assert info["left_out"] == ["reference.png"]
    assert client.request("set_fps", fps=25) == {"fps": 25}
    with pytest.raises(CommandError, match="fps"):
        client.request("set_fps", fps=-1)
    for payload, code in [
        (b"\x00\x01 binary junk", "bad_request"),
        (b'{"v": 2, "command": "health"}', "version"),
        (b'{"v": 1, "command": "explode"}', "unknown_command"),
    ]:
        reply = Reply.model_validate_json(client.request_raw(payload))
        assert reply.error.code == code
    health = Health.model_validate(client.request("health"))
    client.close()
    assert process.poll() is None
    assert health.state == "running" and health.counters["frames_published"] > 0
    assert health.counters["rejected_bad_request"] == 2  # junk + fps=-1
    assert health.counters["rejected_version"] == 1 and health.counters["rejected_unknown_command"] == 1
    assert health.last_error and "unknown_command" in health.last_error


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_stops_cleanly_on_signal(ports, recorded_run, sig):
    process = start_service("imageserver", "--source", "replay")
    wait_healthy(connect("127.0.0.1", ports["control"]), process)
    code, output = stop(process, sig)
    assert code == 0
    assert "imageserver stopped" in output


def test_once_mode_reports_finished(ports, tmp_path):
    from semservo.imagefiles import write_image

    for index in range(3):
        write_image(tmp_path / f"f{index}.tif", np.full((64, 80), index * 1000, np.uint16), magnification=5000)
    process = start_service("imageserver", "--replay-dir", str(tmp_path), "--once", "--fps", "100")
    control = connect("127.0.0.1", ports["control"])
    wait_healthy(control, process)
    client = ControlClient(control, timeout_s=1)
    import time

    deadline = time.monotonic() + 5
    while (health := Health.model_validate(client.request("health"))).state != "finished":
        assert time.monotonic() < deadline, health
        time.sleep(0.05)
    client.close()
    assert health.counters["frames_published"] == 3
    stop(process)


def test_unreadable_replay_folder_fails_at_start_with_a_clear_error(ports, tmp_path):
    process = start_service("imageserver", "--replay-dir", str(tmp_path / "nowhere"))
    code = process.wait(20)
    output = process.stdout.read()
    assert code != 0
    assert "no folder of frames" in output and "nowhere" in output


def test_a_labs_adapter_runs_in_the_image_server_and_takes_scan_settings(ports, monkeypatch):
    """The worked example of docs/instruments.md, as a real process: frames with the
    adapter's metadata over ZeroMQ, its focus set through the control socket, and what
    it cannot do refused in its own words."""
    monkeypatch.setenv("SEMSERVO_IMAGESERVER__ADAPTER_OPTIONS", '{"rows": 128, "cols": 160, "pixel_size_nm": 50}')
    process = start_service("imageserver", "--adapter", "examples.adapters.pattern_sem:PatternSEM", "--fps", "50")
    control = ControlClient(connect("127.0.0.1", ports["control"]), timeout_s=5, retries=1)
    subscriber = FrameSubscriber(connect("127.0.0.1", ports["frames"]), max_message_bytes=2**24)
    try:
        wait_healthy(connect("127.0.0.1", ports["control"]), process)
        frame = subscriber.receive(timeout_s=10)
        assert frame is not None and frame.pixels.shape == (128, 160)
        header = frame.header
        assert (header.source, header.pixel_size_nm, header.detector) == ("pattern-sem", 50.0, "SE")
        assert header.magnification is None  # the adapter does not say: unknown
        assert control.request("set_scan", working_distance_mm=4.2) == {"working_distance_mm": 4.2}
        for _ in range(100):
            frame = subscriber.receive(timeout_s=2)
            if frame is not None and frame.header.working_distance_mm == 4.2:
                break
        assert frame.header.working_distance_mm == 4.2
        with pytest.raises(CommandError, match="one magnification"):
            control.request("set_scan", magnification=3000)
        assert control.request("info")["adapter"] == "examples.adapters.pattern_sem:PatternSEM"
    finally:
        subscriber.close()
        control.close()
        stop(process)
