"""`semservo calibrate` on the real processes (fake lab with the emulated NV 40/3 on TCP
serial, image server on the simulated SEM, stage service): the hysteresis it measures
from the images must be the one the emulator has."""

from __future__ import annotations

import json

import numpy as np
import pytest

from semservo.calibration import sweep_voltages
from semservo.cli import main
from semservo.config import Settings
from semservo.launcher import Launcher, spec
from semservo.simulation.piezo import Hysteresis
from semservo.stage_model import BranchModel, load_model
from tests.conftest import run_lab_faster

pytestmark = pytest.mark.integration

SPEEDUP = 20


@pytest.fixture
def stage_lab(ports, monkeypatch, tmp_path):
    run_lab_faster(monkeypatch, SPEEDUP)
    launcher = Launcher(Settings(), tuple(spec(name) for name in ("fakelab", "imageserver", "stage")),
                        out=(tmp_path / "launcher.log").open("w"))
    launcher.start(timeout_s=90)
    yield launcher
    launcher.stop()


def emulated_loop_width(axis: str, low_v: float, high_v: float, step_v: float) -> float:
    """The emulator's static loop over the same sweep (after coming down to ``low_v``)."""
    hysteresis = Hysteresis(axis)
    hysteresis.apply(high_v)
    rising, falling = {}, {}
    for voltage, direction in sweep_voltages(low_v, high_v, step_v):
        (rising if direction > 0 else falling)[voltage] = hysteresis.apply(voltage)
    stroke = max(rising.values()) - min(rising.values())
    return max(falling.get(v, rising[v]) - rising[v] for v in rising) / stroke


def test_calibrate_recovers_the_emulated_hysteresis(stage_lab, tmp_path, capsys):
    out = tmp_path / "x.json"
    code = main(["calibrate", "--axis", "x", "--step", "5", "--settle", "0.1", "--out", str(out)])
    printed = capsys.readouterr().out
    assert code == 0, printed
    assert "simulator truth" in printed and "model written to" in printed

    model = load_model(out)
    assert isinstance(model, BranchModel)
    calibration = json.loads(out.read_text())["calibration"]
    assert len(calibration["sweep"]) == 2 * 23 + 1
    assert (tmp_path / "x.png").stat().st_size > 10_000

    # The images measure where the stage went to within tens of nanometres of the truth...
    assert calibration["true_error_um"]["mean"] < 0.05
    assert calibration["true_error_um"]["max"] < 0.2
    # ...so the loop is the emulator's: the one the truth draws, and its static loop
    # (creep during the sweep widens it a little).
    assert calibration["loop_width_percent"] == pytest.approx(calibration["true_loop_width_percent"], abs=0.3)
    static = 100 * emulated_loop_width("x", -19.0, 96.0, 5.0)
    assert calibration["loop_width_percent"] == pytest.approx(static, abs=1.5)
    assert 95 < calibration["stroke_um"] < 106

    # The fitted branches give the voltages the truth needed, within a few hundred nm of
    # travel (a volt is about 0.9 um).
    for point in calibration["sweep"]:
        branch = model.increasing if point["direction"] > 0 else model.decreasing
        assert abs(np.polyval(branch, point["true_displacement_um"]) - point["voltage"]) < 1.5


def test_calibrate_without_a_stage_service_fails_clearly(ports, monkeypatch, tmp_path, capsys):
    monkeypatch.setenv("SEMSERVO_REQUEST_TIMEOUT_S", "0.3")
    out = tmp_path / "never.json"
    assert main(["calibrate", "--axis", "y", "--out", str(out), "--frame-timeout", "1"]) == 1
    assert "calibration failed" in capsys.readouterr().err
    assert not out.exists()
