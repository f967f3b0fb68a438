"""The fake lab as a real process: the NV 40/3 emulator over a pseudo-terminal and TCP
through pyserial with raw bytes, the true pose, and simulated frames via the image server."""

from __future__ import annotations

import re
import time

import pytest
import serial

from semservo import nv40
from semservo.config import Settings, connect
from semservo.estimation import MotionEstimator
from semservo.transport import CommandError, ControlClient, FrameSubscriber
from tests.integration.helpers import start_service, stop, wait_healthy

pytestmark = pytest.mark.integration


@pytest.fixture
def fakelab(ports):
    process = start_service("fakelab", "--speedup", "50")
    control_endpoint = connect("127.0.0.1", ports["fakelab_control"])
    wait_healthy(control_endpoint, process)
    control = ControlClient(control_endpoint, timeout_s=5, retries=1)
    info = control.request("info")
    yield process, control, info
    control.close()
    stop(process)


def exchange(port: serial.Serial, raw: bytes, wait_s: float = 0.3) -> bytes:
    """Send raw bytes, return everything the device sent back within ``wait_s`` (it
    ends replies with XON, so stop there)."""
    port.reset_input_buffer()
    port.write(raw)
    received = b""
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        chunk = port.read(port.in_waiting or 1)
        received += chunk
        if received.endswith(nv40.XON) or (raw == b"\r" and received.endswith(b">")):
            break
    return received


def framed(*lines: str) -> bytes:
    return nv40.XOFF + b"".join(line.encode() + b"\r" for line in lines) + nv40.XON


@pytest.fixture
def pty_port(fakelab):
    _, _, info = fakelab
    assert re.fullmatch(r"/dev/pts/\d+", info["serial_pty"])
    port = serial.Serial(info["serial_pty"], baudrate=nv40.BAUD_RATE, timeout=0.05, xonxoff=False)
    yield port
    port.close()


def test_every_command_over_the_pseudo_terminal(pty_port, fakelab):
    _, control, _ = fakelab
    port = pty_port
    assert exchange(port, b"\r") == b"NV403CLE>"
    assert exchange(port, b"ver\r") == framed("NV40/3CLE V5.09", "date: 2012-03-14", "serial no.: 10112")
    assert exchange(port, b"dspvmin\r") == framed("dspvmin,-20.000")
    assert exchange(port, b"dspvmax\r") == framed("dspvmax,130.000")
    assert exchange(port, b"dspclmin,1\r") == framed("dspclmin,1,0.000")
    assert exchange(port, b"dspclmax,1\r") == framed("dspclmax,1,80.000")
    assert exchange(port, b"acdescr,2\r") == framed("acdescr,2,TRITOR100")
    status = int(exchange(port, b"stat,0\r").strip(nv40.XOFF + nv40.XON + b"\r").split(b",")[2])
    assert status & nv40.STATUS_ACTUATOR_READY and not status & nv40.STATUS_REMOTE
    # Knob mode: set is ignored, as on the device.
    assert exchange(port, b"set,0,50.000\r") == framed()
    assert exchange(port, b"rk,0\r") == framed("rk,0,38.000")
    # Remote mode: set moves the stage.
    assert exchange(port, b"setk,0,1\r") == framed()
    assert int(exchange(port, b"stat,0\r").strip(nv40.XOFF + nv40.XON + b"\r").split(b",")[2]) & nv40.STATUS_REMOTE
    assert exchange(port, b"set,0,50.000\r") == framed()
    assert exchange(port, b"rk,0\r") == framed("rk,0,50.000")
    assert exchange(port, b"measure\r") == framed("aw,50.000,38.000,38.000")
    # setall is ignored unless every channel is remote.
    assert exchange(port, b"setall,40,41,42\r") == framed()
    assert exchange(port, b"measure\r") == framed("aw,50.000,38.000,38.000")
    for channel in (1, 2):
        exchange(port, f"setk,{channel},1\r".encode())
    assert exchange(port, b"setall,40.000,41.000,42.000\r") == framed()
    assert exchange(port, b"measure\r") == framed("aw,40.000,41.000,42.000")
    # Closed loop: accepted, but the actuator has no sensor, so it stays open loop.
    assert exchange(port, b"cloop,0,1\r") == framed()
    assert exchange(port, b"cloop,0\r") == framed("cloop,0,0")
    # The true pose follows: x moved with channel 0.
    pose = control.request("pose")
    assert pose["voltages"] == [40.0, 41.0, 42.0]


@pytest.mark.parametrize(
    "raw, code",
    [
        (b"move,0,1\r", nv40.ERROR_UNKNOWN_COMMAND),
        (b"set,3,10\r", nv40.ERROR_UNKNOWN_CHANNEL),
        (b"rk,x\r", nv40.ERROR_UNKNOWN_CHANNEL),
        (b"set,0\r", nv40.ERROR_MISSING_PARAMETER),
        (b"setall,1,2\r", nv40.ERROR_MISSING_PARAMETER),
        (b"set,0,131\r", nv40.ERROR_OUT_OF_RANGE),
        (b"set,0,-20.5\r", nv40.ERROR_OUT_OF_RANGE),
        (b"set,0,abc\r", nv40.ERROR_OUT_OF_RANGE),
        (b"setk,0,2\r", nv40.ERROR_OUT_OF_RANGE),
        (b"setall,1,2,999\r", nv40.ERROR_OUT_OF_RANGE),
    ],
    ids=["unknown-command", "bad-channel", "non-numeric-channel", "missing-value", "setall-missing",
         "over-range", "under-range", "not-a-number", "bad-flag", "setall-out-of-range"],
)
def test_error_replies_over_the_pseudo_terminal(pty_port, raw, code):
    assert exchange(pty_port, raw) == framed(f"ErrorCode,{code}")
    assert exchange(pty_port, b"rk,0\r") == framed("rk,0,38.000")  # nothing moved, still answering


def test_the_same_device_over_tcp_as_a_pyserial_url(fakelab, ports):
    _, _, info = fakelab
    assert info["serial_tcp"] == f"socket://127.0.0.1:{ports['serial_tcp']}"
    port = serial.serial_for_url(info["serial_tcp"], timeout=0.05)
    try:
        assert exchange(port, b"\r") == b"NV403CLE>"
        assert exchange(port, b"setk,1,1\r") == framed()
        assert exchange(port, b"set,1,30.5\r") == framed()
        assert exchange(port, b"rk,1\r") == framed("rk,1,30.500")
        assert exchange(port, b"nonsense\r") == framed(f"ErrorCode,{nv40.ERROR_UNKNOWN_COMMAND}")
    finally:
        port.close()


def test_a_serial_move_shows_in_the_pose_and_the_simulated_frames(fakelab, ports):
    process, control, info = fakelab
    imageserver = start_service("imageserver", "--fps", "50")
    try:
        wait_healthy(connect("127.0.0.1", ports["control"]), imageserver)
        frames = FrameSubscriber(connect("127.0.0.1", ports["frames"]), max_message_bytes=Settings().max_message_bytes)
        before = frames.receive(timeout_s=10)
        assert before is not None and before.header.source == "sim"
        assert before.header.shape == (512, 512) and before.header.magnification == 1200
        port = serial.serial_for_url(info["serial_tcp"], timeout=0.05)
        exchange(port, b"setk,0,1\r")
        exchange(port, b"set,0,44.000\r")
        port.close()
        time.sleep(0.3)  # 15 simulated seconds: settled
        frames.receive(timeout_s=10)  # a frame that may have been scanned during the move
        after = frames.receive(timeout_s=10)
        frames.close()
        # The true poses when the two frames were scanned (mid-scan times in their labels).
        def scanned_at(frame):
            return float(re.search(r"t=([\d.]+)s", frame.header.label).group(1))

        pose_before = control.request("pose", t_s=scanned_at(before))
        pose_after = control.request("pose", t_s=scanned_at(after))
        moved_um = pose_after["x_um"] - pose_before["x_um"]
        assert 4.0 < moved_um < 8.0  # 6 V up, continuing the rise from home, open loop
        motion = MotionEstimator(before.pixels).estimate(after.pixels)
        pixel_um = before.header.pixel_size_nm / 1000
        assert motion.dx == pytest.approx(moved_um / pixel_um, abs=0.2)
        assert motion.dy == pytest.approx((pose_after["y_um"] - pose_before["y_um"]) / pixel_um, abs=0.2)
        with pytest.raises(CommandError, match="future"):
            control.request("pose", t_s=1e9)
    finally:
        stop(imageserver)


def test_rotation_stage_and_bad_requests(fakelab):
    _, control, _ = fakelab
    sent = control.request("set_rotation_stage", rotation_deg=2.5)
    assert sent["targets_deg"]["rotation_deg"] == 2.5 and sent["settles_in_s"] > 0  # it turns at its own speed
    time.sleep(sent["settles_in_s"] + 0.05)
    assert control.request("pose")["rotation_deg"] == pytest.approx(2.5, abs=0.01)
    halted = control.request("set_rotation_stage", halt=True)
    assert halted["settles_in_s"] == 0
    from semservo.transport import CommandError

    with pytest.raises(CommandError, match="spin: Extra inputs are not permitted"):
        control.request("set_rotation_stage", spin=1)
    with pytest.raises(CommandError, match="preset must be one of"):
        control.request("set_preset", preset="moon")
    assert control.request("set_preset", preset="noisy")["preset"]["dwell_ns"] == 180


def test_semservo_fakelab_prints_where_the_serial_port_is(ports):
    import subprocess
    import sys

    process = subprocess.Popen([sys.executable, "-m", "semservo", "fakelab", "--speedup", "10"],
                               stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        lines = [process.stdout.readline() for _ in range(2)]
    finally:
        code, _ = stop(process)
    assert re.search(r"pseudo-terminal\): /dev/pts/\d+", lines[0])
    assert f"socket://127.0.0.1:{ports['serial_tcp']}" in lines[1]
    assert code == 0
