"""``semservo up``: start everything, show frames flowing, report deaths, stop cleanly."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import pytest

from semservo.config import connect
from semservo.transport import ControlClient, ServiceUnavailable

pytestmark = pytest.mark.integration


def up(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "semservo", "up", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )


def read_until(process: subprocess.Popen, pattern: str, timeout_s: float = 30.0) -> str:
    """Read the launcher's output until a line matches; return everything read."""
    seen = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = process.stdout.readline()
        if not line:
            break
        seen.append(line)
        if re.search(pattern, line):
            return "".join(seen)
    raise AssertionError(f"no line matching {pattern!r}; output:\n{''.join(seen)}")


def pid_of(output: str, name: str) -> int:
    return int(re.search(rf"{name} healthy \(pid (\d+)", output).group(1))


def test_up_check_shows_frames_flowing_and_exits_zero(ports, recorded_run):
    # Exactly what the README's first command runs: simulated hardware at real speed
    # (a frame takes 0.46 s, longer than a health request's timeout).
    result = subprocess.run(
        [sys.executable, "-m", "semservo", "up", "--check", "--frames", "4"],
        capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    output = result.stdout
    assert "fakelab healthy" in output and "imageserver healthy" in output and "estimator healthy" in output
    assert f"tcp://127.0.0.1:{ports['frames']}" in output  # what runs where
    assert f"socket://127.0.0.1:{ports['serial_tcp']}" in output
    assert "source sim" in output  # simulated hardware by default
    assert "check passed: 5 motion estimates" in output
    assert "check passed: 4 valid frames" in output
    assert re.search(r"512x512 uint8", output)
    assert "imageserver | " in output  # service logs streamed with a prefix
    assert "imageserver stopped (exit code 0)" in output


def test_ctrl_c_stops_every_service(ports, recorded_run):
    launcher = up("--speedup", "10")
    output = read_until(launcher, r"watching frames")
    child = pid_of(output, "imageserver")
    os.killpg(launcher.pid, signal.SIGINT)  # what Ctrl-C in a terminal does
    try:
        # Read while waiting: a launcher blocked on a full pipe cannot finish stopping.
        rest, _ = launcher.communicate(timeout=45)
    except subprocess.TimeoutExpired:
        launcher.kill()
        raise AssertionError(f"the launcher did not stop; its output:\n{launcher.communicate()[0]}") from None
    assert launcher.returncode == 0, rest
    assert "imageserver stopped" in rest
    with pytest.raises(ProcessLookupError):
        os.kill(child, 0)
    with pytest.raises(ServiceUnavailable):
        ControlClient(connect("127.0.0.1", ports["control"]), timeout_s=0.2, retries=1).request("health")


def test_a_dead_service_is_reported_at_once_and_restarted_when_asked(ports, recorded_run):
    launcher = up("--restart", "--speedup", "10")
    try:
        output = read_until(launcher, r"watching frames")
        first = pid_of(output, "imageserver")
        os.kill(first, signal.SIGKILL)
        output = read_until(launcher, r"imageserver died", timeout_s=10)
        assert "exit code -9" in output
        read_until(launcher, r"restarting imageserver", timeout_s=10)
        # the replacement answers health on the same control socket
        client = ControlClient(connect("127.0.0.1", ports["control"]), timeout_s=0.5, retries=20)
        health = client.request("health")
        client.close()
        assert health["pid"] != first and health["state"] == "running"
    finally:
        launcher.send_signal(signal.SIGTERM)
        launcher.wait(20)


def test_without_restart_a_death_fails_the_check(ports, tmp_path):
    # A folder of one frame at a very low rate keeps --check waiting while we kill the service.
    from semservo.imagefiles import write_image
    import numpy as np

    write_image(tmp_path / "only.png", np.zeros((64, 64), np.uint8))
    launcher = up("--check", "--frames", "1000", "--replay-dir", str(tmp_path), "--fps", "1")
    output = read_until(launcher, r"checking: waiting")
    os.kill(pid_of(output, "imageserver"), signal.SIGKILL)
    assert launcher.wait(20) == 1
    rest = launcher.stdout.read()
    assert "imageserver died" in rest and "check FAILED (imageserver down)" in rest


def test_a_service_that_cannot_start_is_reported(ports, tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "semservo", "up", "--check", "--replay-dir", str(tmp_path / "missing")],
        capture_output=True, text=True, timeout=60,
    )
    assert result.returncode == 1
    assert "failed to start: imageserver exited with code" in result.stdout
    assert "no folder of frames" in result.stdout


def test_a_service_whose_port_is_taken_says_so_and_exits(ports):
    """A second semservo on the same machine: the service names the port and the setting
    instead of dying in a ZeroMQ traceback."""
    import socket

    with socket.socket() as squatter:
        squatter.bind(("127.0.0.1", ports["stage_control"]))
        squatter.listen()
        result = subprocess.run([sys.executable, "-m", "semservo", "service", "stage"],
                                capture_output=True, text=True, timeout=60)
    assert result.returncode == 1
    assert f"127.0.0.1:{ports['stage_control']}" in result.stderr
    assert "SEMSERVO_STAGE__*_PORT" in result.stderr
    assert "Traceback" not in result.stderr


def test_the_fake_lab_whose_serial_port_is_taken_says_so_in_one_line(ports):
    import socket

    with socket.socket() as squatter:
        squatter.bind(("127.0.0.1", ports["serial_tcp"]))
        squatter.listen()
        for command in (["service", "fakelab"], ["fakelab", "--no-pty"]):
            result = subprocess.run([sys.executable, "-m", "semservo", *command], capture_output=True, text=True,
                                    timeout=60)
            assert result.returncode == 1, result.stderr
            assert "fakelab: cannot bind its port" in result.stderr and "SEMSERVO_FAKELAB__*_PORT" in result.stderr
            assert "Traceback" not in result.stderr


def test_up_check_beside_a_running_stack_does_not_take_its_services_for_ours(ports):
    """Another semservo already answers on these ports: ours cannot start, and the check
    must say so instead of reporting the other stack's services as healthy."""
    from tests.integration.helpers import start_service, stop, wait_healthy

    other = start_service("fakelab", "--no-pty")
    try:
        wait_healthy(connect("127.0.0.1", ports["fakelab_control"]), other)
        result = subprocess.run([sys.executable, "-m", "semservo", "up", "--check", "--frames", "2"],
                                capture_output=True, text=True, timeout=120)
    finally:
        stop(other)
    assert result.returncode == 1, result.stdout
    assert "fakelab healthy" not in result.stdout
    assert re.search(r"another process \(pid \d+|fakelab exited with code 1", result.stdout), result.stdout


def test_up_on_a_watched_folder_the_simulated_sem_saves_into(ports, tmp_path):
    """The README's path for a real SEM, with the simulated one saving its frames (FEI
    TIFFs with a data bar, written in chunks) where the image server watches."""
    folder = tmp_path / "acquisition"
    result = subprocess.run(
        [sys.executable, "-m", "semservo", "up", "--check", "--frames", "3", "--watch-dir", str(folder),
         "--sim-saves-frames"],
        capture_output=True, text=True, timeout=180,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "source watch" in result.stdout and "data bar 64 rows cropped" in result.stdout
    assert "512x512" in result.stdout  # the frame without its bar
    assert len(list(folder.glob("frame*.tif"))) >= 3


def test_up_refuses_a_watch_folder_that_is_not_there(ports, tmp_path):
    missing = subprocess.run([sys.executable, "-m", "semservo", "up", "--watch-dir", str(tmp_path / "nope")],
                             capture_output=True, text=True, timeout=60)
    assert missing.returncode == 2 and "no folder to watch" in missing.stderr
    alone = subprocess.run([sys.executable, "-m", "semservo", "up", "--sim-saves-frames"],
                           capture_output=True, text=True, timeout=60)
    assert alone.returncode == 2 and "--sim-saves-frames needs --watch-dir" in alone.stderr
