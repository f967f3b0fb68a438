"""Time to target (issue #28): the in-process timed loop on a continuously scanning
simulated SEM, the position law beside the paper's, the experiment's resumable trials.
Behaviour only (frames, truth, refusals); how fast is the benchmark's business."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from semservo import jsontext, reproduce
from semservo.reproduce import loop, report

pytestmark = pytest.mark.integration


def start(case: str, fraction: float, angle: float = 0.7) -> tuple[float, float]:
    radius = fraction * reproduce.field_um(case)
    return radius * math.cos(angle), radius * math.sin(angle)


def test_the_position_law_reaches_the_target_in_a_few_fresh_frames_acting_on_fresh_frames_only():
    result = loop.run_timed_trial("noisy", "position", start("noisy", 0.15), seed=3)
    assert result["outcome"] == "converged", result["reason"]
    assert result["fresh_frames"] <= 6 and result["true_error_px"] <= 0.1
    moves = [r for r in result["records"] if r.get("action") == "moved"]
    # Each move lands during the next scan, which is not acted on: one stale scan per move.
    assert result["frames_scanned"] == result["fresh_frames"] + len(moves)
    stale = [t for t, _, fresh in result["trace"] if not fresh]
    assert len(stale) == len(moves)
    assert result["seconds"] == pytest.approx(result["frames_scanned"] * result["frame_time_s"], rel=1e-6)


def test_a_trial_reports_where_the_sample_rested_beside_the_frames_mean_pose():
    """The true final error is the last frame's mean pose, the vibration's mean over its
    scan included; the stage's own error leaves the vibration out (what a move can fix)."""
    lab = loop.Lab("high-magnification", 1)
    interval = (0.30, 0.30 + lab.settings.frame_time_s)
    shown, resting = lab.true_pose(interval), lab.true_pose(interval, vibration=False)
    disturbances = lab.world.disturbances
    vibration = [np.subtract(disturbances.offset(t), disturbances.offset(t, vibration=False))
                 for t in np.linspace(*interval, 32)]
    assert shown - resting == pytest.approx(np.mean(vibration, axis=0), abs=1e-9)
    assert float(np.hypot(*(shown - resting))) > 1e-4  # a scan does not average 7 Hz away
    result = loop.run_timed_trial("high-magnification", "position", start("high-magnification", 0.05), seed=2)
    assert result["outcome"] == "converged", result["reason"]
    assert result["stage_error_px"] <= 0.1 and result["stage_error_px"] != result["true_error_px"]


def test_without_a_calibration_the_position_law_converges_without_overshoot():
    result = loop.run_timed_trial("noisy", "position", start("noisy", 0.15, 2.0), seed=4, stage_model="uncalibrated")
    assert result["outcome"] == "converged", result["reason"]
    assert result["true_error_px"] <= 0.1
    assert result["overshoot_px"] < 1.0  # from 77 px away


def test_the_stage_models_move_the_stage_as_named():
    moved = {}
    for model in ("calibrated", "other-stage+15%", "other-stage-15%", "uncalibrated"):
        lab = loop.Lab("optimal", 1, stage_model=model)
        before = lab.true_pose((0.0, 0.01))
        lab.move(8.0, 0.0, at=0.5)
        moved[model] = float(lab.true_pose((2.0, 2.01))[0] - before[0])
    # A model made for a stage that moves 15 % more: this stage moves 1 / 1.15 as far.
    assert moved["other-stage+15%"] / moved["calibrated"] == pytest.approx(1 / 1.15, rel=0.03)
    assert moved["other-stage-15%"] / moved["calibrated"] == pytest.approx(1 / 0.85, rel=0.03)
    assert moved["uncalibrated"] / 8.0 > 1.0  # the nominal stroke undersells the piezo's gain


@pytest.mark.timeout(300)  # four trials; slow on a loaded machine
def test_the_experiment_keeps_each_trial_and_resumes(tmp_path, monkeypatch):
    checkpoint = tmp_path / "time_to_target.partial.jsonl"
    quiet = lambda total: reproduce.Progress("time", total, quiet=True)  # noqa: E731
    arguments = dict(checkpoint=checkpoint, trials=1, cases=("noisy",), models=("calibrated", "uncalibrated"),
                     baseline=False, offsets=("0.5 px",))
    first = reproduce.experiment_time_to_target(True, quiet, **arguments)
    rows = first["rows"]
    # 2 laws x 2 stage models on each law's own frames, and each law on the other frames
    # with the calibrated model.
    assert len(rows) == 6 and len(checkpoint.read_text().splitlines()) == 6
    assert {(r["law"], r["stage_model"], r["frames"]) for r in rows} == {
        ("position", "calibrated", "partial"), ("position", "uncalibrated", "partial"),
        ("position", "calibrated", "whole"), ("paper", "calibrated", "whole"), ("paper", "uncalibrated", "whole"),
        ("paper", "calibrated", "partial")}
    assert all(r["outcome"] == "converged" for r in rows if r["law"] == "position")
    assert all(r["partial_frames_used"] == 0 for r in rows if r["frames"] == "whole")
    # Run again: every trial comes from the checkpoint, none is run.
    monkeypatch.setattr(reproduce, "time_trial", lambda job: pytest.fail(f"re-ran {job['key']}"))
    again = reproduce.experiment_time_to_target(True, quiet, **arguments)
    assert [r["key"] for r in again["rows"]] == [r["key"] for r in rows]
    # The report's tables come out of it, the targets judged per preset.
    again.update(quick=True)
    assert any("noisy" in line for line in report.time_to_target_headline_lines(again))
    targets = report.time_to_target_targets(again)
    assert len(targets) == 3 and "met" in targets[2]
    jsontext.dumps(again)  # strict JSON: nothing in it that a JSON reader cannot load
    report.plot_time_to_target(again, tmp_path / "time.png")
    assert (tmp_path / "time.png").read_bytes()[:4] == b"\x89PNG"


def test_a_trial_taught_in_another_lab_is_the_trial_taught_in_its_own():
    # Trials of one seed share the teaching; the lab that starts from it continues the
    # simulated SEM's charging and noise, so nothing differs (a fresh noise generator of
    # the same seed would repeat the reference's own noise: a false correlation peak).
    args = ("optimal", "position", start("optimal", 0.05))
    own = loop.run_timed_trial(*args, seed=5)
    taught = loop.teach(loop.Lab("optimal", 5), loop.TimedSettings())
    shared = loop.run_timed_trial(*args, seed=5, taught=taught)
    assert shared["trace"] == own["trace"] and shared["true_error_px"] == own["true_error_px"]
