"""The service glue as contracts (issue #24): every command declared once and answered,
arguments checked before a handler sees them, the docs generated from the declarations,
capabilities asked of a source (a lab's adapter serves focus sweeps), one camera-to-stage
transform from the settings, typed replies in the OpenAPI."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from semservo.errors import BadRequest, CommandError, http_status
from semservo.protocol import controller, estimator, fakelab, imageserver, markdown, stage

ROOT = Path(__file__).parents[2]


def all_handlers():
    from services.controller.commands import handlers as controller_handlers
    from services.estimator.commands import handlers as estimator_handlers
    from services.fakelab.commands import handlers as fakelab_handlers
    from services.imageserver.commands import handlers as imageserver_handlers
    from services.stage.commands import handlers as stage_handlers

    return {"stage": stage_handlers, "controller": controller_handlers, "estimator": estimator_handlers,
            "imageserver": imageserver_handlers, "fakelab": fakelab_handlers}


def test_every_declared_command_has_a_handler_and_nothing_else_is_answered():
    declared = {"stage": stage.COMMANDS, "controller": controller.COMMANDS, "estimator": estimator.COMMANDS,
                "imageserver": imageserver.COMMANDS, "fakelab": fakelab.COMMANDS}
    for service, handlers in all_handlers().items():
        assert handlers.commands is declared[service]
        assert handlers.missing() == [], f"{service} declares commands it does not answer"
        assert "health" in declared[service], "health is every service's"


def test_the_architecture_map_shows_the_tables_generated_from_the_declarations():
    from semservo.protocol.__main__ import BEGIN, END

    text = (ROOT / "docs" / "architecture.md").read_text()
    shown = text[text.index(BEGIN) + len(BEGIN):text.index(END)].strip()
    assert shown == markdown().strip(), "run: python -m semservo.protocol --write docs/architecture.md"


def test_the_estimators_report_gets_longer_than_a_ports_default_from_every_caller():
    """A teach asks the estimator's report first (a dead one named in seconds); a busy,
    live estimator answered it past 1 s and the teach was a 503. The command declares its
    own timeout, so the gateway's and the controller's ports both give it 5 s."""
    from semservo.protocol import ServicePort

    asked = []

    class Client:
        endpoint = "tcp://127.0.0.1:1"

        def request(self, name, *, timeout_s=None, **args):
            asked.append((name, timeout_s))
            return {"reference": None, "rotation": False, "measure_rotation": False, "measure_tilts": False,
                    "tilt_reference": None, "last_tilt": None, "tilt_error": None, "precision": "single",
                    "latest_frame_seq": None, "last_estimate": None}

    ServicePort(Client(), shared=True).call(estimator.REPORT)
    ServicePort(Client(), timeouts={"measure": 4.0}).call(estimator.REPORT)
    assert asked == [("report", 5.0), ("report", 5.0)]


@pytest.mark.parametrize("args, field", [
    ({"targets": {"x": float("nan")}}, "targets.x"),
    ({"targets": {"x": True}}, "targets.x"),
    ({"targets": {"x": "1"}}, "targets.x"),
    ({"targets": {}}, "targets"),
    ({"targets": {"x": 1.0}, "speed": 3}, "speed"),
    ({"targets": {"x": 1.0}, "relative": 1}, "relative"),
])
def test_arguments_are_checked_before_a_handler_sees_them(args, field):
    """No socket: the stage's table refuses what its declaration does not take, naming
    the field, and the core is never called (it is None here)."""
    from services.stage.commands import handlers

    with pytest.raises(BadRequest) as refused:
        handlers.dispatch(None, "move", args)
    assert refused.value.code == "bad_request" and refused.value.message.startswith(field)


def test_one_error_type_one_status_table():
    assert http_status("bad_request") == 422 and http_status("travel_limit") == 409
    assert http_status("stage_unavailable") == 503 and http_status("no_such_run") == 404
    assert http_status("unauthorized") == 401 and http_status("too_large") == 413
    assert isinstance(BadRequest("x"), CommandError)


def test_every_json_endpoint_answers_a_typed_model():
    from services.gateway.app import create_app
    from services.gateway.core import GatewayCore
    from services.gateway.records import RunStore

    schema = create_app(GatewayCore({}, RunStore(":memory:"))).openapi()
    untyped = []
    for path, operations in schema["paths"].items():
        for method, operation in operations.items():
            content = operation["responses"].get("200", operation["responses"].get("201", {})).get("content", {})
            body = content.get("application/json", {}).get("schema")
            if body is None:
                continue  # an image, a CSV, a file
            typed = "$ref" in body or "$ref" in body.get("items", {})
            if not typed:
                untyped.append(f"{method.upper()} {path}: {body}")
    assert not untyped, untyped


def test_calibration_uses_the_camera_to_stage_transform_of_the_settings(monkeypatch):
    """`semservo calibrate` once built its own transform and dropped the rotation sign."""
    from semservo import calibration, cli
    from semservo.control import CameraToStage

    monkeypatch.setenv("SEMSERVO_CONTROLLER__AXIS_SIGNS", "[-1, 1]")
    monkeypatch.setenv("SEMSERVO_CONTROLLER__ORIENTATION_DEG", "90")
    monkeypatch.setenv("SEMSERVO_CONTROLLER__ROTATION_SIGN", "-1")
    monkeypatch.setenv("SEMSERVO_CONTROLLER__TILT_SIGNS", "[1, -1]")
    seen = {}

    class Capture:
        started_v = last_v = None  # as a Calibrator before its first move

        def __init__(self, stage, next_frame, **options):
            seen.update(options)

        def run(self, low, high, step):
            raise calibration.CalibrationError("captured")

    monkeypatch.setattr(calibration, "Calibrator", Capture)
    monkeypatch.setattr(cli, "calibration_ports", lambda settings, **kwargs: (None, None, None, lambda: None))
    assert cli.main(["calibrate", "--no-truth"]) == 1
    expected = CameraToStage((-1, 1), 90.0, -1, (1, -1))
    assert seen["camera"] == expected
    from semservo.config import Settings

    assert Settings().controller.camera_to_stage() == expected, "the controller's and the gateway's, the same"


def test_a_labs_adapter_that_can_focus_serves_a_focus_sweep():
    """Sweeps are asked of the source's capabilities, not of its class: the worked
    example adapter sets its working distance, so the image server sweeps it (pausing its
    stream, setting the focus back after)."""
    from semservo.instruments import capabilities
    from services.imageserver.commands import ImageServer, handlers
    from services.imageserver.core import ImageServerCore
    from services.imageserver.sources import adapter_source
    from services.imageserver.sweep import decode_sweep

    source = adapter_source("examples.adapters.pattern_sem:PatternSEM", {"rows": 64, "cols": 64}, fps=50)
    server = ImageServer(ImageServerCore(source, fps=50))
    try:
        assert {"focus", "scan_settings"} <= capabilities(source)
        deadline = time.monotonic() + 10
        while source.last_image is None and time.monotonic() < deadline:  # a frame says the working distance
            try:
                source.acquire()
            except Exception:  # noqa: BLE001 - NotReady until the first scan is in
                time.sleep(0.02)
        started = handlers.dispatch(server, "start_sweep", {"working_distances_um": [-4.0, -2.0, 0.0, 2.0, 4.0]})
        while (result := handlers.dispatch(server, "sweep", {"sweep_id": started["sweep_id"]}))["state"] == "scanning":
            assert time.monotonic() < deadline + 10, "the sweep never ended"
            time.sleep(0.02)
        assert result["state"] == "done", result.get("error")
        frames = decode_sweep(result).astype(float)
        sharpness = [np.mean(np.diff(frame, axis=1) ** 2) / frame.var() for frame in frames]  # scale-free
        assert int(np.argmax(sharpness)) == 2, sharpness  # in focus at the working distance the sweep centred on
        assert source.inner.working_distance_mm == pytest.approx(10.0), "the focus is set back after the sweep"
    finally:
        server.close()
        source.close()


def test_a_source_that_cannot_focus_refuses_a_sweep_in_words(tmp_path):
    from semservo.imagefiles import write_image
    from services.imageserver.commands import ImageServer, handlers
    from services.imageserver.core import ImageServerCore
    from services.imageserver.sources import ReplaySource

    write_image(tmp_path / "a.png", np.zeros((32, 32), np.uint8))
    server = ImageServer(ImageServerCore(ReplaySource(tmp_path), fps=10))
    with pytest.raises(CommandError) as refused:
        handlers.dispatch(server, "start_sweep", {"working_distances_um": [-1.0, 0.0, 1.0]})
    assert refused.value.code == "not_supported" and "replay" in refused.value.message


def test_the_stage_state_folder_of_a_fresh_system_is_removed_when_the_process_exits():
    """Every test and benchmark system gets a fresh stage-state folder; one left behind
    per system filled /tmp with hundreds of empty folders per CI run."""
    import subprocess
    import sys

    script = ("from semservo.launcher import fresh_port_environment\n"
              "import os\n"
              "folder = fresh_port_environment()['SEMSERVO_STAGE__STATE_DIR']\n"
              "assert os.path.isdir(folder)\n"
              "print(folder)\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=True)
    folder = Path(done.stdout.strip())
    assert folder.name.startswith("semservo-stage-")
    assert not folder.exists()


def test_the_launcher_stops_a_service_only_after_those_that_call_it_while_stopping():
    """The controller ends a run through the stage and the estimator, the stage lets go
    of the (emulated) amplifier: each group stops together, after the one before."""
    from semservo.launcher import SERVICES, _stop_groups

    groups = _stop_groups([service.name for service in SERVICES])
    assert groups == [["gateway", "controller"], ["estimator", "imageserver", "stage"], ["fakelab"]]
    assert sorted(name for group in groups for name in group) == sorted(service.name for service in SERVICES)
    assert _stop_groups(["fakelab", "imageserver", "stage"]) == [["imageserver", "stage"], ["fakelab"]]
    assert _stop_groups(["fakelab", "other"]) == [["fakelab"], ["other"]]


def test_the_controller_and_the_gateway_start_without_the_estimators_libraries():
    """Most of a service's start is imports: the controller and the gateway use the
    estimation package for constants and conventions only, and the gateway draws a report
    only when asked; numba, FFTW and matplotlib are seconds of their start."""
    import subprocess
    import sys

    code = ("import sys, services.controller.main, services.gateway.main; "
            "print(' '.join(name for name in ('numba', 'pyfftw', 'matplotlib') if name in sys.modules))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert loaded.stdout.strip() == ""


def test_a_service_process_ends_as_python_would_without_its_finalization(tmp_path):
    """``end_process`` skips the interpreter's teardown (0.3-0.9 s per service, seconds
    per stack stopped) but not its duties: threads that are not daemons finish, atexit
    handlers run, the log and standard streams are flushed, the exit code is kept."""
    import subprocess
    import sys

    marker = tmp_path / "written-by-the-thread"
    script = ("import atexit, logging, pathlib, sys, threading, time\n"
              "from semservo.service import end_process\n"
              "logging.basicConfig(stream=sys.stderr, level=logging.INFO)\n"
              f"marker = pathlib.Path({str(marker)!r})\n"
              "threading.Thread(target=lambda: (time.sleep(0.3), marker.write_text('done'))).start()\n"
              "atexit.register(lambda: print('atexit ran', flush=False))\n"
              "print('buffered line', end='')\n"
              "logging.getLogger('service').info('stopped')\n"
              "end_process(3)\n"
              "print('never reached')\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert done.returncode == 3, done.stderr
    assert marker.read_text() == "done"
    assert done.stdout == "buffered lineatexit ran\n"
    assert "INFO:service:stopped" in done.stderr
