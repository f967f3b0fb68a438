"""Displacement -> voltage models: the lab's branches with direction memory, linear, files."""

from __future__ import annotations

import numpy as np
import pytest

from semservo.simulation.piezo import voltage_for
from semservo.stage_model import BranchModel, LinearModel, load_model, save_model


def test_tritor_model_uses_the_branch_of_the_direction_of_motion():
    model = BranchModel.tritor("x")
    model.reset(20.0)
    assert model.voltage_for(50.0) == pytest.approx(voltage_for("x", "increasing", 50.0))
    assert model.voltage_for(60.0) == pytest.approx(voltage_for("x", "increasing", 60.0))
    # Reversal: the decreasing branch's slope, continuous at the reversal point (no
    # jump between branches), merging onto the decreasing branch over a long move.
    top = voltage_for("x", "increasing", 60.0)
    down = model.voltage_for(55.0)
    offset = top - voltage_for("x", "decreasing", 60.0)
    assert down == pytest.approx(voltage_for("x", "decreasing", 55.0) + offset * np.exp(-5.0 / model.merge_um))
    assert down < top
    assert model.voltage_for(55.0) == pytest.approx(down)  # no motion keeps the branch
    far = model.voltage_for(5.0)
    assert far == pytest.approx(voltage_for("x", "decreasing", 5.0), abs=0.15 * offset)


def test_linear_model_and_round_trip_through_a_file(tmp_path):
    linear = LinearModel(gain_um_per_v=0.9, offset_v=-20.0)
    assert linear.voltage_for(45.0) == pytest.approx(30.0)
    for model in (linear, BranchModel.tritor("y")):
        loaded = load_model(save_model(model, tmp_path / "model.json"))
        assert type(loaded) is type(model)
        for target in np.linspace(5, 95, 7):
            assert loaded.voltage_for(target) == pytest.approx(model.voltage_for(target))


def test_bad_model_files_are_clear_errors(tmp_path):
    (tmp_path / "bad.json").write_text('{"kind": "magic"}')
    with pytest.raises(ValueError, match="not a displacement model"):
        load_model(tmp_path / "bad.json")
    with pytest.raises(ValueError, match="not a displacement model"):
        load_model(tmp_path / "missing.json")


def test_a_followed_voltage_leaves_the_model_in_step_with_the_axis():
    """After a reversal (a minor loop's offset active), a reconnect or an uncommanded change
    makes the model follow the voltage read back; the next 0.03 um correction asked for an
    11 V jump (the inverse was taken with the offset, which was then dropped)."""
    for axis in ("x", "y"):
        model = BranchModel.tritor(axis)
        model.voltage_for(40.0)
        here = model.voltage_for(30.0)  # a reversal: the decreasing branch, offset by the gap
        assert abs(model.offset_v) > 5
        model.follow_voltage(here, here)  # the link came back and reads the same voltage
        assert model.voltage_for(model.position_um) == pytest.approx(here, abs=1e-6)
        assert abs(model.voltage_for(model.position_um - 0.027) - here) < 0.1
        model.follow_voltage(here + 3.0, here)  # a knob turned the axis up
        assert abs(model.voltage_for(model.position_um + 0.05) - (here + 3.0)) < 0.2
