"""The controller's loop, one step at a time (services/controller/run.py): each step is a
function of the run and the estimate, so each rule is checked alone, without a stage."""

from __future__ import annotations

import math
from collections import deque

import pytest

from semservo.control import ControlLaw, LawStep, PositionLaw, TiltLaw
from semservo.messages import MotionEstimate
from semservo.protocol.controller import RunSettings
from services.controller.run import (
    DECIDING_SWEEPS, FOREIGN_ESTIMATES_TO_FAIL, STALL_SWEEPS, TILT_SIGNIFICANCE, IterationRecord, Run, Tilts, admit, decide, gate, judge, measure, tilt_step,
)


def make_run(**settings) -> Run:
    settings = RunSettings(**settings)
    planar = tuple(dof for dof in settings.dofs if dof in ("x", "y", "rotation"))
    tilts = tuple(dof for dof in settings.dofs if dof in ("alpha", "beta"))
    return Run(id="r", reference_id="ref", settings=settings, started_at_ns=0, stage_at_start={},
               law=ControlLaw(planar), tilts=Tilts(TiltLaw(tilts)) if tilts else None, last_command_ns=1_000,
               recent=deque())


def estimate(dx: float = 1.0, dy: float = 0.0, *, seq: int = 1, confidence: float = 0.9, started_ns: int = 2_000,
             reference: str = "ref", pixel_size_nm: float | None = 100.0, rotation_deg: float = 0.0,
             **tilt) -> MotionEstimate:
    return MotionEstimate(seq=seq, reference_id=reference, dx_px=dx, dy_px=dy, rotation_deg=rotation_deg,
                          confidence=confidence, snr_db=20.0, filtered=False, pixel_size_nm=pixel_size_nm,
                          frame_acquired_at_ns=started_ns + 10, frame_published_at_ns=started_ns + 20,
                          frame_scan_started_at_ns=started_ns, frame_source_interval_s=(seq * 1.0, seq * 1.0 + 0.5),
                          published_at_ns=started_ns + 30, estimation_ms=1.0, latency_ms=1.0, **tilt)


def feed(run: Run, errors, **options):
    """Fresh estimates through gate, measure and judge; the first verdict that ends the run."""
    for seq, error in enumerate(errors, 1):
        assert gate(run, estimate(error, seq=seq, **options)) is None
        verdict = judge(run, measure(run, estimate(error, seq=seq, **options)))
        if verdict is not None and verdict.ending:
            return verdict
    return None


def test_admit_tolerates_two_estimates_in_flight_against_another_reference_not_three():
    run = make_run()
    for _ in range(FOREIGN_ESTIMATES_TO_FAIL - 1):
        verdict = admit(run, estimate(reference="other"))
        assert verdict.ending is None and verdict.action is None  # ignored, not recorded
    assert admit(run, estimate()) is None and run.foreign == 0, "one of its own resets the count"
    for _ in range(FOREIGN_ESTIMATES_TO_FAIL):
        verdict = admit(run, estimate(reference="other"))
    assert verdict.ending == "failed" and "reference changed" in verdict.reason and "other" in verdict.reason


def test_gate_holds_stale_and_unconfident_estimates_and_fails_without_a_pixel_size():
    run = make_run(lost_after=3)
    unknown = gate(run, estimate(pixel_size_nm=None))
    assert unknown.ending == "failed" and "SEMSERVO_IMAGESERVER__PIXEL_SIZE_NM" in unknown.reason
    stale = gate(run, estimate(started_ns=run.last_command_ns - 1))
    assert stale.action.startswith("held: stale") and stale.ending is None and run.held_stale == 1
    for _ in range(2):
        assert gate(run, estimate(confidence=0.1)).action == "held: low confidence"
    assert gate(run, estimate()) is None and run.low_confidence == 0, "a confident one resets the count"
    for _ in range(3):
        lost = gate(run, estimate(confidence=0.1))
    assert lost.ending == "failed" and "scene lost" in lost.reason


def test_convergence_is_judged_on_the_mean_or_on_each_frame():
    on_mean = feed(make_run(converge_frames=2), [0.15, -0.04])
    assert on_mean is not None and on_mean.ending == "converged"
    assert feed(make_run(converge_frames=2, converge_on="each"), [0.15, -0.04]) is None
    assert feed(make_run(converge_frames=2, hold=True), [0.01, 0.01, 0.01]) is None, "a hold goes on"


def test_errors_either_side_of_the_target_do_not_average_to_convergence():
    """A run overshooting across moves measured (+0.37, -0.31), (-0.07, +0.10), (-0.37,
    +0.41) px: the mean vector is 0.07 px, the run 0.55 px from its goal."""
    run = make_run(converge_frames=3)
    errors = [(0.37, -0.31), (-0.07, 0.10), (-0.37, 0.41)]
    for seq, (dx, dy) in enumerate(errors, 1):
        verdict = judge(run, measure(run, estimate(dx, dy, seq=seq)))
    assert verdict is None, "not converged: the errors' sizes average 0.45 px"


def test_a_run_whose_error_stops_falling_fails_saying_so():
    """The run the issue found left servoing at 2.9 px after 329 iterations."""
    run = make_run(stall_after=20, max_iterations=10_000)
    verdict = feed(run, [2.9 + 0.05 * math.sin(seq) for seq in range(40)])
    assert verdict is not None and verdict.ending == "failed" and verdict.reason.startswith("no progress")
    assert "2.9" in verdict.reason and "tolerance 0.1" in verdict.reason
    assert run.fresh_frames == 21, "the best, then stall_after frames without beating it by 10 %"


def test_a_slow_but_steady_approach_and_a_held_target_are_progress():
    falling = [20.0 * 0.95 ** seq for seq in range(150)]  # 5 % a frame: beats its best by 10 % every 3 frames
    assert feed(make_run(stall_after=20, max_iterations=10_000, converge_frames=1), falling).ending == "converged"
    holding = [0.05, -0.04, 0.06] * 40  # within tolerance all along: holding is not stalling
    assert feed(make_run(stall_after=20, hold=True, max_iterations=10_000), holding) is None


def test_a_tilt_run_is_not_stalled_before_its_sweeps_have_had_their_say():
    run = make_run(dofs=["x", "y", "alpha", "beta"], stall_after=5, max_iterations=10_000)
    assert feed(run, [3.0] * 30) is None, "no sweep measured yet: x, y alone do not judge a tilt run"
    record = IterationRecord.of(estimate())
    for seq in range(1, STALL_SWEEPS + 3):
        tilted = estimate(3.0, seq=seq, alpha_deg=2.0, beta_deg=-1.0, tilt_confidence=0.9, tilt_seq=seq,
                          tilt_scan_started_at_ns=10 * seq)
        tilt_step(run, tilted, record)
        verdict = judge(run, measure(run, tilted, new_sweep=True))
        if verdict is not None:
            break
    assert verdict is not None and verdict.ending == "failed" and "tilts alpha +2.000 deg" in verdict.reason


def sweep(run: Run, seq: int, alpha: float, beta: float, sigma: float | None) -> IterationRecord:
    """One fresh focus sweep's measurement through tilt_step; its record (whether a step
    was made: ``tilt_action == "moved"``)."""
    record = IterationRecord.of(estimate())
    tilted = estimate(0.0, seq=seq, alpha_deg=alpha, beta_deg=beta, tilt_confidence=0.9, tilt_seq=seq,
                      tilt_scan_started_at_ns=10_000 * seq,
                      tilt_uncertainty_deg=None if sigma is None else (sigma, sigma))
    step = tilt_step(run, tilted, record)
    assert (step is not None) == (record.tilt_action == "moved")
    return record


def test_tilts_are_not_moved_on_an_error_their_sweeps_cannot_tell_from_zero_but_pooled_until_they_can():
    """Runs on a real texture measured to +-0.1 degree chased that noise and stalled."""
    run = make_run(dofs=["alpha", "beta"], tolerance_tilt_deg=0.1)
    noisy = sweep(run, 1, 0.15, -0.02, sigma=0.1)
    assert noisy.tilt_action.startswith(f"held: within {TILT_SIGNIFICANCE:g} standard")
    assert run.tilts.within is None, "0.15 degree is not within the 0.1 tolerance: the run does not converge on it"
    # Sweeps of the same pose pool: the mean's standard error falls as 1 / sqrt(n).
    second = sweep(run, 2, 0.05, 0.02, sigma=0.1)
    assert second.tilt_pooled == 2 and second.tilt_mean_deg["alpha"] == pytest.approx(0.10)
    assert second.tilt_spread_deg["alpha"] == pytest.approx(0.1 / math.sqrt(2))
    assert second.tilt_action.startswith("held") and run.tilts.within is not None, "a mean within tolerance: may converge"
    # A clear error is acted on, on the mean, and a move starts a new pool.
    run = make_run(dofs=["alpha", "beta"], tolerance_tilt_deg=0.1)
    for seq, alpha in enumerate((0.9, 1.1), 1):
        clear = sweep(run, seq, alpha, 0.0, sigma=0.1)
        if clear.tilt_action == "moved":
            break
    assert clear.tilt_action == "moved" and clear.tilt_pooled == 1, "0.9 degree is 9 standard errors: moved at once"
    run.tilts.moved(settled_ns=15_000)
    assert run.tilts.since_move == [] and run.tilts.moves == 1
    after = sweep(run, 2, 0.3, 0.0, sigma=0.1)
    assert after.tilt_pooled == 1 and after.tilt_action == "moved", "3 standard errors, from a fresh pool"


def test_a_tilt_run_pooling_to_tell_an_error_from_zero_is_deciding_not_stalled_for_a_while():
    """A 5-DOF demo on tescan_aperture failed as 'no progress' after 6 sweeps held at
    beta +0.205 +- ~0.1 degree (tolerance 0.1): the stall rule ended the run while its
    sweeps were still being pooled to tell that error from zero."""
    run = make_run(dofs=["alpha", "beta"], tolerance_tilt_deg=0.1, stall_after=5, max_iterations=10_000)
    verdict = None
    for seq in range(1, DECIDING_SWEEPS + 2):
        # Alternating 0.5 and -0.1: a mean of 0.2 beyond tolerance, each sweep +-0.6.
        record = sweep(run, seq, 0.5 if seq % 2 else -0.1, 0.0, sigma=0.6)
        assert record.tilt_action.startswith("held: within"), record.tilt_action
        tilted = estimate(0.0, seq=seq, alpha_deg=run.tilts.last_error["alpha"], beta_deg=0.0, tilt_confidence=0.9,
                          tilt_seq=seq, tilt_scan_started_at_ns=10_000 * seq)
        for _ in range(6):  # the frames between sweeps
            verdict = judge(run, measure(run, tilted, new_sweep=False))
            assert verdict is None or seq >= DECIDING_SWEEPS, f"stalled while deciding, after {seq} sweeps"
        verdict = judge(run, measure(run, tilted, new_sweep=True))
        if verdict is not None:
            assert seq >= DECIDING_SWEEPS, f"stalled while deciding, after {seq} sweeps"
            break
        assert run.tilts.deciding() == (seq < DECIDING_SWEEPS)
    assert verdict is not None and verdict.ending == "failed" and "no progress" in verdict.reason, \
        "pooled this long without telling: the run ends, saying so"


def test_tilts_without_standard_errors_are_judged_on_the_latest_sweep_alone():
    run = make_run(dofs=["alpha", "beta"], tolerance_tilt_deg=0.1)
    assert sweep(run, 1, 0.3, 0.0, sigma=None).tilt_action == "moved"
    assert sweep(run, 2, 0.04, 0.0, sigma=None).tilt_mean_deg == {"alpha": 0.04, "beta": 0.0}


def test_a_run_whose_sweeps_cannot_tell_the_tilts_fails_saying_why_not_at_its_iteration_limit():
    """Runs on sparse particles whose every sweep was refused (pinned too loosely against
    the taught plane) ran to their 600-iteration limit; now the third fresh sweep in a
    row that cannot tell the tilts ends the run with its reason. A sweep that can resets
    the count; a stale one does not count."""
    run = make_run(dofs=["x", "y", "alpha", "beta"], max_iterations=10_000)
    why = "against the taught plane the tilts would be pinned to +-0.13 degree only"

    def refused(seq: int, started_ns: int) -> None:
        record = IterationRecord.of(estimate())
        tilt_step(run, estimate(1.0, seq=seq, tilt_confidence=0.0, tilt_seq=seq, tilt_scan_started_at_ns=started_ns,
                                tilt_reason=why), record)

    def judged(seq: int):
        return judge(run, measure(run, estimate(1.0, seq=seq), new_sweep=False))

    refused(1, 10_000)
    refused(2, 20_000)
    assert judged(2) is None
    sweep(run, 3, 2.0, -1.0, sigma=0.05)  # one that can: the count starts again
    assert run.tilts.refused_in_row == 0
    run.tilts.moved(settled_ns=100_000)
    refused(4, 50_000)  # scanned during the move: stale, not counted
    assert run.tilts.refused_in_row == 0
    for seq in (5, 6, 7):
        refused(seq, 100_000 * seq)
    verdict = judged(7)
    assert verdict.ending == "failed" and "tilts lost: 3 focus sweeps in a row" in verdict.reason
    assert why in verdict.reason


def test_decide_lets_the_position_law_chain_moves_and_the_papers_law_make_one():
    run = make_run(max_move_um=10.0, moves_per_frame=3)
    run.law = PositionLaw(("x", "y"))
    far = LawStep((100.0,), 1e4, 1.0, (), {"x_um": 30.0, "y_um": -40.0})
    chained = decide(run, far, None)
    assert chained.saturated and math.hypot(*chained.targets.values()) == pytest.approx(30.0)
    assert chained.targets["x"] / chained.targets["y"] == pytest.approx(30.0 / -40.0)
    paper = decide(make_run(max_move_um=10.0, moves_per_frame=3), far, None)  # ControlLaw
    assert math.hypot(*paper.targets.values()) == pytest.approx(10.0)


def test_decide_saturates_moves_and_turns_and_judges_divergence_above_its_floor():
    run = make_run(max_move_um=10.0, max_turn_deg=2.0, diverge_iterations=2)
    big = LawStep((100.0,), 1e4, 0.5, (1.0,), {"x_um": 30.0, "y_um": -40.0, "rotation_deg": 5.0})
    decision = decide(run, big, None)
    assert decision.saturated and math.hypot(*decision.targets.values()) == pytest.approx(10.0)
    assert decision.targets["x"] == pytest.approx(6.0) and decision.turns["rotation_deg"] == 2.0
    assert decision.turn_saturated and decision.diverging is None
    small = LawStep((0.3,), 0.09, 0.5, (0.0,), {"x_um": 0.01})
    for _ in range(5):  # noise near the target: never divergence, however small the cost's minimum
        assert decide(run, small, None).diverging is None
    run = make_run(diverge_iterations=2)
    decide(run, LawStep((2.0,), 4.0, 0.5, (0.0,), {"x_um": 0.1}), None)
    decide(run, LawStep((5.0,), 25.0, 0.5, (0.0,), {"x_um": 0.1}), None)
    assert decide(run, LawStep((6.0,), 36.0, 0.5, (0.0,), {"x_um": 0.1}), None).diverging.startswith("diverging")


def test_recovery_reads_run_journals_only_and_says_nothing_of_the_stages_log(tmp_path, caplog):
    """A frightening line on every first start: the stage's command log (a .jsonl in the
    same folder) was read as a dead controller's journal."""
    import logging

    from services.controller.core import ControllerCore

    (tmp_path / "stage-commands.jsonl").write_text('{"time_ns": 1, "direction": "sent", "text": "set,0,1"}\n')
    (tmp_path / "20260101-000000-abcdef.jsonl").write_text("")  # a run's journal torn at its first line
    with caplog.at_level(logging.ERROR, logger="controller"):
        assert ControllerCore(stage=None, runs_dir=tmp_path).recover() == []
    messages = [record.getMessage() for record in caplog.records]
    assert len(messages) == 1 and "20260101-000000-abcdef" in messages[0] and "delete it" in messages[0]


def test_each_degree_of_freedom_is_named_once_and_the_schema_says_so():
    # A repeated name is a malformed body (the schema's uniqueItems), refused where the
    # request is read; gamma and rotation are two names of one degree of freedom.
    assert RunSettings.model_json_schema()["properties"]["dofs"]["uniqueItems"] is True
    with pytest.raises(ValueError, match="each degree of freedom once"):
        RunSettings(dofs=["x", "x", "x", "x", "x"])
    assert RunSettings(dofs=["x", "rotation", "gamma"]).dofs == ["x", "rotation", "gamma"]


def test_a_new_foreshortening_undone_by_the_estimator_restarts_what_the_position_law_knows_of_the_turn():
    from services.controller.run import foreshortening_changed

    run = make_run(dofs=["x", "y", "rotation", "alpha", "beta"], tolerance_deg=0.05)
    # The sweep before a tilt move of (-1.65, -2.93) degrees, then the one after it.
    assert not foreshortening_changed(run, estimate(alpha_deg=1.65, beta_deg=2.93, tilt_seq=15))
    assert not foreshortening_changed(run, estimate(alpha_deg=1.65, beta_deg=2.93, tilt_seq=15))
    assert foreshortening_changed(run, estimate(alpha_deg=-0.036, beta_deg=-0.012, tilt_seq=16))
    # Near the goal, sweeps that differ by their noise leave the turn as it was read.
    assert not foreshortening_changed(run, estimate(alpha_deg=0.06, beta_deg=-0.09, tilt_seq=17))
    assert not foreshortening_changed(run, estimate(alpha_deg=None, beta_deg=None, tilt_seq=18))
    # A sweep that cannot tell the tilts leaves the estimator undoing the last ones that could.
    far = make_run(dofs=["x", "y", "rotation", "alpha", "beta"], tolerance_deg=0.05)
    assert not foreshortening_changed(far, estimate(tilt_seq=None))  # nothing measured yet: nothing undone
    assert foreshortening_changed(far, estimate(alpha_deg=4.0, beta_deg=-3.0, tilt_seq=1))  # the first sweep
    assert not foreshortening_changed(far, estimate(alpha_deg=None, beta_deg=None, tilt_seq=2))
    assert not foreshortening_changed(far, estimate(alpha_deg=4.0, beta_deg=-3.0, tilt_seq=3))
    without_rotation = make_run(dofs=["x", "y", "alpha", "beta"])
    assert not foreshortening_changed(without_rotation, estimate(alpha_deg=3.0, beta_deg=3.0, tilt_seq=1))
    assert not foreshortening_changed(without_rotation, estimate(alpha_deg=0.0, beta_deg=0.0, tilt_seq=2))

    # What the restart is for: a law sure of a turn read through the old foreshortening
    # takes the truth, 0.08 degree away, for noise; restarted, it turns.
    def settled_law() -> PositionLaw:
        law = PositionLaw(("x", "y", "rotation"), tolerance_px=0.1, tolerance_deg=0.05)
        for frame in range(12):
            start = frame * 0.6
            law.step(0.01, -0.01, -0.002, 70.0, frame_interval_s=(start, start + 0.36), now_s=start + 0.4)
        assert law.converged
        return law

    sure = settled_law()
    step = sure.step(0.01, -0.01, -0.08, 70.0, frame_interval_s=(7.2, 7.56), now_s=7.6)
    assert "rotation_deg" not in step.move
    restarted = settled_law()
    restarted.view_moved()
    step = restarted.step(0.01, -0.01, -0.08, 70.0, frame_interval_s=(7.2, 7.56), now_s=7.6)
    assert step.move["rotation_deg"] == pytest.approx(0.08, rel=0.25) and not restarted.converged


def test_a_run_that_leaves_x_and_y_alone_never_reports_a_translation_error_it_did_not_judge():
    """A turn-only run judges the turn: its records carry no translation error (None, not
    the 0.000 px a law without planar DOFs would estimate), and its reason says the view
    is still off in x and y, by how much (a new user's turn-only run reported 'converged:
    0.000 px' with the view 22.6 px off)."""
    run = make_run(dofs=["rotation"], converge_frames=2)
    verdict = None
    for seq in (1, 2):
        measurement = measure(run, estimate(20.0, -15.0, seq=seq, rotation_deg=0.01))
        assert measurement.mean_error_px is None
        verdict = judge(run, measurement)
    assert verdict.ending == "converged"
    assert "0.000 px" not in verdict.reason
    assert "turn's mean error over the last 2 fresh frames 0.010 deg" in verdict.reason
    assert "not servoed: x, y (the view is +20.00 px in x, -15.00 px in y off)" in verdict.reason
    turning = PositionLaw(("rotation",))
    turning.step(20.0, -15.0, 0.5, 100.0, 1.0, frame_interval_s=(0.0, 0.5), now_s=0.6, scan_time_s=0.5)
    assert all(math.isnan(value) for value in turning.planar_estimate()), "it estimates no planar error"


def test_a_converged_position_law_run_says_the_turn_it_judged_not_the_frames_mean():
    """The position law judges the turn on its own estimate: the reason gives that, not the
    mean over the last frames, one of them from before the correction (a demo reported
    'the turn's mean error 0.147 deg, under 0.05 deg' with the true turn 0.025)."""
    run = make_run(dofs=["x", "y", "rotation"], converge_frames=3, tolerance_deg=0.05)
    run.law = PositionLaw(("x", "y", "rotation"), tolerance_px=0.1, tolerance_deg=0.05)
    for frame in range(12):
        start = frame * 0.6
        run.law.step(0.01, -0.01, -0.002, 70.0, frame_interval_s=(start, start + 0.36), now_s=start + 0.4)
    assert run.law.converged
    verdict = None
    for seq, turn in enumerate((0.44, -0.002, -0.002), 1):  # the first scanned before the turn's correction
        verdict = judge(run, measure(run, estimate(0.01, -0.01, seq=seq, rotation_deg=turn)))
    assert verdict is not None and verdict.ending == "converged"
    judged_turn = run.law.turn_estimate()[0]
    assert judged_turn < 0.05
    assert f"the position law's turn {judged_turn:.3f} deg" in verdict.reason and "0.147" not in verdict.reason


def test_a_run_along_x_alone_judges_x_and_says_how_far_off_y_is():
    """An x-only run converges on x (before, the paper's law asked the whole translation of
    it and could never converge; the position law's estimate already was x's alone), and
    its reason names the axis and the view's error along the one it left."""
    run = make_run(dofs=["x"], converge_frames=2)
    verdict = feed(run, [0.03, -0.02], dy=27.0)
    assert verdict is not None and verdict.ending == "converged"
    assert "fresh frames 0.025 px in x, under 0.1 px" in verdict.reason
    assert "not servoed: y (the view is +27.00 px in y off)" in verdict.reason
    assert judge(make_run(dofs=["x", "y"], converge_frames=1),
                 measure(make_run(dofs=["x", "y"]), estimate(0.03, 27.0))) is None, "x and y: y is judged"
