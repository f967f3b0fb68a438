"""OpenFIBSEM (``fibsem`` 0.5.3, the ``semservo[openfibsem]`` extra, which ``./dev test``
installs): its DemoMicroscope as the microscope, its frames rendered by semservo's
simulated SEM at the demo's own stage position and beam shift
(:class:`semservo.openfibsem.SimulatedDemoFrames`). The loop closes through fibsem's own
calls (``stable_move``, ``beam_shift``), and is judged by the simulation's truth."""

from __future__ import annotations

import importlib.metadata
import math
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

os.environ.setdefault("FIBSEM_SIM_NO_DELAY", "1")  # the demo's one-second sleep per stage move

from fibsem import utils  # noqa: E402 - after the demo is told not to sleep
from fibsem.alignment import AlignmentSubsystem, _apply_shift, beam_shift_alignment_v2  # noqa: E402
from fibsem.structures import BeamType, ImageSettings  # noqa: E402

from semservo.errors import CommandError  # noqa: E402
from semservo.instruments import DeviceError, load_plugin, IMAGE_SOURCE_GROUP  # noqa: E402
from semservo.openfibsem import OpenFibsemMotion, OpenFibsemSource, Positioner, SimulatedDemoFrames, session, units  # noqa: E402,E501
from services.stage.physical import PhysicalLimits, PhysicalStageCore  # noqa: E402

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]
#: The paper's optimal condition: x1200 on 512 pixels (0.177 um), 720 ns/px.
HFW_UM = 212.3 / 1200 * 512
ELECTRON = BeamType.ELECTRON


def demo_microscope(folder: Path):
    microscope, _settings = utils.setup_session(session_path=str(folder), manufacturer="Demo",
                                                ip_address="localhost", setup_logging=False)
    return microscope


@pytest.fixture
def demo(tmp_path):
    microscope = demo_microscope(tmp_path)
    return microscope, SimulatedDemoFrames(microscope)


def test_a_microscope_is_named_by_its_url_and_connected_once_per_process():
    address = session.Address.parse("openfibsem://Thermo@10.0.0.1?beam=ion&beam_limit_um=5")
    assert (address.manufacturer, address.host, address.options) == ("Thermo", "10.0.0.1",
                                                                     {"beam": "ion", "beam_limit_um": "5"})
    with pytest.raises(ValueError, match="unknown option"):
        session.Address.parse("openfibsem://Demo@localhost?speed=fast")
    with pytest.raises(DeviceError, match="openfibsem://MANUFACTURER@HOST"):
        OpenFibsemMotion.open("socket://127.0.0.1:5592")
    with pytest.raises(DeviceError, match="stage_move must be stable or relative"):
        OpenFibsemMotion.open("openfibsem://Demo@localhost?stage_move=sideways")
    driver = OpenFibsemMotion.open("openfibsem://Demo@localhost?beam_limit_um=3")
    again = OpenFibsemMotion.open("openfibsem://Demo@localhost?beam_limit_um=3")
    assert driver.microscope is again.microscope and again.origin == driver.origin  # a reconnect reads the same
    assert driver.identify()["model"] == "Demo DemoMicroscope" and driver.axes()["beam_x"].travel == (-3.0, 3.0)
    assert float(driver.microscope.get_stage_position().z) == pytest.approx(session.DEMO_WORKING_HEIGHT_M)


def test_one_opencv_in_the_environment_the_one_semservo_pins():
    """fibsem asks for opencv-python-headless, the package semservo pins: two OpenCV
    packages in one environment (one would overwrite the other's cv2) never happen."""
    installed = {name for name in ("opencv-python", "opencv-python-headless", "opencv-contrib-python",
                                   "opencv-contrib-python-headless") if _installed(name)}
    assert installed == {"opencv-python-headless"}
    assert importlib.metadata.version("opencv-python-headless") == "5.0.0.93"
    wanted = [re.split(r"[<>=!~; \[]", requirement)[0].lower()
              for requirement in importlib.metadata.requires("fibsem") or [] if "extra ==" not in requirement]
    assert "opencv-python-headless" in wanted and "opencv-python" not in wanted
    assert importlib.metadata.version("fibsem") == "0.5.3"


def _installed(name: str) -> bool:
    try:
        importlib.metadata.version(name)
        return True
    except importlib.metadata.PackageNotFoundError:
        return False


def test_units_and_signs_are_converted_once_and_back():
    # fibsem's alignment corrects a content shift (dx, dy) by stable_move(dx, -dy) or beam_shift(-dx, dy)
    assert units.stage_move_m(2.0, 3.0) == (-2e-6, 3e-6)
    assert units.beam_shift_m(2.0, 3.0) == (2e-6, -3e-6)
    for signs in (units.STAGE_SIGNS, units.BEAM_SIGNS, (1, 1)):
        metres = units.to_metres(1.25, -0.5, signs)
        assert units.to_micrometres(*metres, signs) == pytest.approx((1.25, -0.5))
    with pytest.raises(ValueError, match="finite"):
        units.stage_move_m(math.nan, 0.0)
    assert units.signs_from_text("1,-1", (1, 1)) == (1, -1) and units.signs_from_text(None, (1, 1)) == (1, 1)
    with pytest.raises(ValueError, match="two of"):
        units.signs_from_text("1,2", (1, 1))


def test_the_signs_agree_with_fibsems_own_alignment_and_with_the_simulated_demo(demo):
    """fibsem's own alignment corrects one measured shift with the stage or with the beam
    (``_apply_shift``): on the simulated demo both move the content alike, and so do
    semservo's x and beam_x (the content moves as units.py says it does)."""
    microscope, frames = demo
    before = np.array(frames.content_um())
    _apply_shift(microscope, 3e-6, 2e-6, ELECTRON, AlignmentSubsystem.STAGE)
    by_stage = np.array(frames.content_um()) - before
    _apply_shift(microscope, 3e-6, 2e-6, ELECTRON, AlignmentSubsystem.BEAM_SHIFT)
    by_beam = np.array(frames.content_um()) - before - by_stage
    assert by_stage == pytest.approx(by_beam, abs=1e-6) and np.hypot(*by_stage) == pytest.approx(math.hypot(3, 2))
    driver = OpenFibsemMotion(microscope)
    for stage_axis, beam_axis, content in (("x", "beam_x", (1.0, 0.0)), ("y", "beam_y", (0.0, 1.0))):
        start = np.array(frames.content_um())
        driver.move_by({stage_axis: 1.0})
        assert np.array(frames.content_um()) - start == pytest.approx(content, abs=1e-6)
        driver.move_by({beam_axis: 1.0})
        assert np.array(frames.content_um()) - start == pytest.approx(2 * np.array(content), abs=1e-6)
    positions = driver.read_positions()
    # x, y from where the driver found the stage; the beam shift absolute: fibsem's alignment left it where the
    # content moved by (-3, -2) um, then beam_x and beam_y moved it by +1 each
    assert positions == pytest.approx({"x": 1.0, "y": 1.0, "beam_x": -2.0, "beam_y": -1.0}, abs=1e-6)
    assert any(entry.text.startswith("stable_move(dx=-1e-06, dy=0,") for entry in driver.log)
    assert any(entry.text.startswith("beam_shift(dx=1e-06, dy=0,") for entry in driver.log)


def test_fibsems_own_alignment_undoes_what_semservos_driver_did_on_the_simulated_demo(tmp_path):
    """Apart from semservo's conversion: fibsem measures with its own cross-correlation
    and corrects with its own signs. It undoes a move of semservo's driver in one step,
    so the driver, the simulated demo and fibsem agree on which way is which."""
    microscope = demo_microscope(tmp_path)
    frames = SimulatedDemoFrames(microscope, disturbances=False)
    settings = ImageSettings(resolution=(512, 512), dwell_time=720e-9, hfw=HFW_UM * 1e-6, beam_type=ELECTRON)
    reference = microscope.acquire_image(image_settings=settings)
    driver = OpenFibsemMotion(microscope)
    for move, subsystem in (({"x": 3.0, "y": -2.0}, AlignmentSubsystem.STAGE),
                            ({"beam_x": -1.5, "beam_y": 2.5}, AlignmentSubsystem.BEAM_SHIFT)):
        before = np.array(frames.content_um())
        driver.move_by(move)
        assert np.array(frames.content_um()) - before == pytest.approx(list(move.values()), abs=1e-9)
        beam_shift_alignment_v2(microscope, reference, subsystem=subsystem)
        # within a pixel (0.18 um): fibsem's default cross-correlation finds whole pixels
        assert np.hypot(*frames.content_um()) < 0.18, (move, frames.content_um())


def test_the_image_source_takes_its_scan_from_the_settings_and_its_metadata_from_the_image(tmp_path):
    microscope = demo_microscope(tmp_path)
    source = load_plugin("openfibsem", IMAGE_SOURCE_GROUP)(microscope=microscope, resolution=[384, 256],
                                                           dwell_ns=250, hfw_um=76.8)
    assert isinstance(source, OpenFibsemSource)
    image = source.acquire()
    assert image.pixels.shape == (256, 384) and image.pixels.dtype == np.uint8
    assert image.acquisition() == {"pixel_size_nm": pytest.approx(200.0), "dwell_ns": 250.0,
                                   "working_distance_mm": pytest.approx(4.0), "high_voltage_kv": 2.0,
                                   "detector": "ETD SecondaryElectrons", "instrument": "Demo DemoMicroscope"}
    assert image.scan_started_at_ns <= image.acquired_at_ns and image.source_interval_s is None  # a microscope's clock
    assert source.set_scan(dwell_ns=500) == {"dwell_ns": 500.0} and source.acquire().dwell_ns == 500.0
    assert source.set_working_distance(4.2) == pytest.approx(4.2) and source.acquire().working_distance_mm == \
        pytest.approx(4.2)
    assert "focus" in source.capabilities() and "scan_settings" in source.capabilities()
    with pytest.raises(ValueError, match="resolution"):
        OpenFibsemSource(microscope=microscope, resolution=[8, 8])


def test_the_adapter_refuses_what_the_microscope_refuses_in_its_words(demo, tmp_path):
    microscope, _frames = demo
    driver = OpenFibsemMotion(microscope, beam_limit_um=5.0)
    driver.move_by({"beam_x": 4.0})
    with pytest.raises(DeviceError, match=r"a beam shift of 6 um in x is beyond its limit -5\.\.5 um "
                                          r"\(beam_limit_um 5 \(this SDK reports no limits\)\)"):
        driver.move_by({"beam_x": 2.0})
    assert driver.read_positions()["beam_x"] == pytest.approx(4.0)  # nothing clipped, nothing moved

    # A microscope whose SDK reports its beam shift limits (as AutoScript does).
    limits = SimpleNamespace(limits_x=SimpleNamespace(min=-3e-6, max=3e-6),
                             limits_y=SimpleNamespace(min=-2e-6, max=2e-6))
    microscope._get_beam = lambda beam_type: SimpleNamespace(beam_shift=SimpleNamespace(limits=limits))
    reported = OpenFibsemMotion(microscope)
    assert reported.axes()["beam_y"].travel == (-2.0, 2.0)
    with pytest.raises(DeviceError, match="beyond its limit -3..3 um \\(the microscope's beam shift limits\\)"):
        reported.move_by({"beam_x": 1.0})  # already at 4 um

    # The stage's range: fibsem's own limits (RangeLimit), in its words.
    from fibsem.structures import FibsemStagePosition

    microscope.move_stage_absolute(FibsemStagePosition(x=0.1 - 2e-6))
    with pytest.raises(DeviceError, match=r"the stage's x would go to 0\.100001 m, outside its range "
                                          r"RangeLimit\(min=-0\.1, max=0\.1\)"):
        OpenFibsemMotion(microscope).move_by({"x": -3.0})  # the content left: the stage towards +x

    # What the SDK itself raises reaches the stage's refusal in its words.
    def refuse(**_move):
        raise RuntimeError("Stage is not homed")

    microscope.stable_move = refuse
    core = PhysicalStageCore("openfibsem:test", open_driver=lambda _url: OpenFibsemMotion(microscope),
                             state_dir=tmp_path, physical=PhysicalLimits(travel={"beam_x": (-2.0, 2.0)}))
    assert core.connect()
    with pytest.raises(CommandError) as refused:
        core.move({"x": -1.0}, relative=True)
    assert refused.value.code == "device_refused"
    assert "stable_move(dx=1e-06, dy=0, beam_type=ELECTRON): RuntimeError: Stage is not homed" in refused.value.message
    with pytest.raises(CommandError) as refused:  # the lab's narrower beam travel: refused before the microscope
        core.move({"beam_x": 2.5})
    assert refused.value.code == "travel_limit"
    assert core.describe()["axes"]["beam_x"]["travel"] == [-2.0, 2.0]


def true_error_px(frames: SimulatedDemoFrames, taught: np.ndarray, pixel_um: float) -> np.ndarray:
    """Where the run left the content: its last scan against the taught pose."""
    return (frames.true_pose(frames.scans[-1:]) - taught) / pixel_um


def test_a_closed_loop_through_fibsems_calls_converges_by_stage_then_by_beam_shift(demo):
    microscope, frames = demo
    positioner = Positioner(microscope, hfw_um=HFW_UM, dwell_ns=720)
    reference = positioner.teach(frames=4)
    pixel_um = reference["pixel_size_nm"] / 1000
    assert pixel_um == pytest.approx(212.3 / 1200, rel=1e-6)
    taught = frames.true_pose(frames.scans[-4:])

    # The stage path: the lab jogs the stage with fibsem's own call; semservo brings it back.
    microscope.stable_move(dx=14e-6, dy=-9e-6, beam_type=ELECTRON)
    run = positioner.run()
    assert run["outcome"]["state"] == "converged", run["outcome"]["reason"]
    assert all(set(record["targets"]) <= {"x", "y"} for record in run["records"] if record.get("targets"))
    error = true_error_px(frames, taught, pixel_um)
    assert np.all(np.abs(error) <= 0.1), error
    assert microscope.get_beam_shift(ELECTRON).x == 0.0  # the beam was not used

    # The beam-shift path: the stage for the approach, the beam for the last micrometres.
    microscope.stable_move(dx=-11e-6, dy=7e-6, beam_type=ELECTRON)
    run = positioner.run(beam_shift_within_um=2.0)
    assert run["outcome"]["state"] == "converged", run["outcome"]["reason"]
    moved = [set(record["targets"]) for record in run["records"] if record.get("targets")]
    assert moved[0] == {"x", "y"} and moved[-1] == {"beam_x", "beam_y"}  # stage, then beam shift
    assert moved.index({"beam_x", "beam_y"}) == len(moved) - sum(axes == {"beam_x", "beam_y"} for axes in moved)
    error = true_error_px(frames, taught, pixel_um)
    assert np.all(np.abs(error) <= 0.1), error
    shift = microscope.get_beam_shift(ELECTRON)
    assert 0.05 < math.hypot(shift.x, shift.y) * 1e6 < 2.0  # the beam made the last micrometres
    sent = [entry["text"] for entry in run["stage_log"] if entry["direction"] == "sent"]
    assert any(text.startswith("stable_move(") for text in sent) and any(text.startswith("beam_shift(") for text in sent)


def test_a_run_asking_for_the_beam_on_a_stage_without_one_is_refused_before_it_moves():
    from semservo.errors import http_status
    from semservo.protocol import LocalPort
    from semservo.simulation.amplifier import SimulatedAmplifier
    from services.controller.core import ControllerCore
    from services.controller.core import RunSettings
    from services.stage.commands import handlers
    from services.stage.core import StageCore

    stage = StageCore("sim://no-beam", open_driver=SimulatedAmplifier.open)
    stage.connect()
    controller = ControllerCore(LocalPort(handlers, stage))
    with pytest.raises(CommandError, match="beam_shift_within_um needs a beam shift beside the stage") as refused:
        controller.start(RunSettings(beam_shift_within_um=1.0), {"id": "r", "pixel_size_nm": 100.0})
    assert refused.value.code == "no_beam_shift" and http_status(refused.value.code) == 409  # valid, not possible here
    assert not stage.watchdog.armed


def test_a_lab_script_positions_with_semservo_in_at_most_ten_lines():
    example = REPO / "examples" / "openfibsem_position.py"
    text = example.read_text()
    blocks = re.findall(r"# --- semservo ---\n(.*?)# --- end semservo ---", text, flags=re.S)
    added = [line for block in blocks for line in block.splitlines() if line.strip()]
    assert blocks and len(added) <= 10, added
    result = subprocess.run([sys.executable, str(example)], capture_output=True, text=True, timeout=300, cwd=REPO,
                            env={**os.environ, "FIBSEM_SIM_NO_DELAY": "1"})
    assert result.returncode == 0, result.stdout + result.stderr
    assert re.search(r"^converged: the position law's estimate 0\.\d+ px", result.stdout, flags=re.M), \
        result.stdout


def test_semservo_up_runs_on_the_openfibsem_adapter_and_the_demo_microscope(ports, tmp_path, monkeypatch):
    """The README's command, as docs/instruments.md gives it for OpenFIBSEM: frames from
    the adapter with the image's metadata, the stage service on the motion driver (stage
    and beam shift, in micrometres), a jog through the gateway's stage service."""
    from semservo.config import Settings, connect
    from semservo.protocol import ServicePort
    from semservo.protocol import stage as stage_protocol
    from semservo.transport import ControlClient

    for name, value in {"FIBSEM_SIM_NO_DELAY": "1", "SEMSERVO_IMAGESERVER__ADAPTER": "openfibsem",
                        "SEMSERVO_IMAGESERVER__ADAPTER_OPTIONS": '{"manufacturer": "Demo", "hfw_um": 100, '
                                                                 '"dwell_ns": 100}',
                        "SEMSERVO_IMAGESERVER__FPS": "5", "SEMSERVO_STAGE__DRIVER": "openfibsem",
                        "SEMSERVO_STAGE__SERIAL_URL": "openfibsem://Demo@localhost",
                        "SEMSERVO_STAGE__ROTATION_STAGE": "none",
                        "SEMSERVO_CONTROLLER__RUNS_DIR": str(tmp_path / "runs"),
                        "SEMSERVO_GATEWAY__DATABASE": str(tmp_path / "runs" / "semservo.sqlite")}.items():
        monkeypatch.setenv(name, value)
    launcher = subprocess.Popen([sys.executable, "-m", "semservo", "up", "--source", "adapter"], cwd=REPO,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    seen = []
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline:
            line = launcher.stdout.readline()
            if not line:
                break
            seen.append(line)
            if "frames flowing" in line:
                break
        output = "".join(seen)
        assert "frames flowing" in output, output
        assert re.search(r"512x512 uint8, 195\.3 nm/px, 100 ns/px, WD 4 mm, 2 kV, ETD SecondaryElectrons, "
                         r"source openfibsem", output), output
        assert "stage driver (openfibsem)" in output and "openfibsem://Demo@localhost" in output
        settings = Settings()
        stage = ServicePort(ControlClient(connect("127.0.0.1", settings.stage.control_port), timeout_s=10, retries=1))
        try:
            state = stage.call(stage_protocol.STATE)
            assert state.kind == "physical" and state.link == "connected" and state.device == "Demo DemoMicroscope"
            assert {axis: info.moves for axis, info in state.axes.items()} == \
                {"x": "stage", "y": "stage", "beam_x": "beam", "beam_y": "beam"}
            moved = stage.call(stage_protocol.MOVE, targets={"x": 2.0, "beam_y": -0.5}, relative=True)
            assert moved.positions_um == pytest.approx({"x": 2.0, "y": 0.0, "beam_x": 0.0, "beam_y": -0.5}, abs=1e-9)
            assert any(entry.text.startswith("stable_move(dx=-2e-06") for entry in stage.call(stage_protocol.LOG).entries)
        finally:
            stage.close()
    finally:
        os.killpg(launcher.pid, signal.SIGINT)
        try:
            rest, _ = launcher.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            launcher.kill()
            rest = launcher.communicate()[0]
    assert launcher.returncode == 0, "".join(seen) + rest
    assert "imageserver stopped (exit code 0)" in rest and "stage stopped (exit code 0)" in rest
