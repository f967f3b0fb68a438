"""The control law (eq. 30-37) as pure functions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semservo.control import (
    NO_OVERSHOOT_GAIN_TIMES_T, AdaptiveGain, CameraToStage, ControlLaw, ExponentialGain, LawStep, PositionTiltLaw, TiltLaw, cost,
    error_vector, interaction_matrix, levenberg_marquardt_velocity, theta_u_interaction,
)


def test_error_and_cost_follow_eq_31_32():
    error = error_vector(3.0, -4.0, 90.0, ("x", "y", "rotation"))
    assert error.tolist() == pytest.approx([3.0, -4.0, math.pi / 2])
    assert cost(error) == pytest.approx(25 + (math.pi / 2) ** 2)
    with pytest.raises(ValueError, match="unknown degrees of freedom"):
        error_vector(0, 0, 0, ("x", "tilt"))


def test_theta_u_interaction_is_visp_cdrc_form():
    # u = z: [u]x rotates x into y; the middle term is +theta/2 [u]x (ViSP cdRc).
    matrix = theta_u_interaction(0.4, (0, 0, 1))
    assert matrix[0, 1] == pytest.approx(-0.2) and matrix[1, 0] == pytest.approx(0.2)
    assert matrix[2, 2] == pytest.approx(1.0)  # about the beam the feature maps one to one
    assert np.allclose(theta_u_interaction(0.0), np.eye(3))
    assert np.allclose(interaction_matrix(("x", "y", "rotation"), 0.3), np.eye(3))


def test_levenberg_marquardt_law_with_identity_halves_the_gain():
    velocity = levenberg_marquardt_velocity(np.array([2.0, -4.0]), np.eye(2), gain=0.5)
    assert velocity.tolist() == pytest.approx([-0.5, 1.0])  # -lambda (2 I)^-1 e


def test_adaptive_gain_grows_with_the_error_within_bounds():
    gain = AdaptiveGain(scale=50, minimum=0.5, maximum=0.8)
    assert gain(np.array([0.1, 0.1])) == 0.5
    assert gain(np.array([30.0, 30.0])) == pytest.approx(0.6)  # sigma_e 30 / 50, equal components still move
    assert gain(np.array([300.0, 0.0])) == 0.8
    exponential = ExponentialGain(at_zero=0.8, at_infinity=0.5)
    assert exponential(np.zeros(2)) == pytest.approx(0.8) and exponential(np.array([1e4, 0])) == pytest.approx(0.5)


@pytest.mark.parametrize("orientation", [0.0, 30.0, -90.0])
def test_camera_to_stage_round_trip_and_signs(orientation):
    transform = CameraToStage(axis_signs=(1, -1), orientation_deg=orientation)
    stage = transform.stage_move_um(10.0, -4.0, pixel_size_nm=200.0)
    assert transform.content_move_px(*stage, pixel_size_nm=200.0) == pytest.approx((10.0, -4.0))
    if orientation == 0.0:
        assert stage == pytest.approx((2.0, 0.8))  # 10 px of 0.2 um; y axis reversed


def test_the_law_drives_a_simulated_plant_to_zero_without_overshoot():
    # Plant: the content moves exactly by the commanded stage move (open-loop model
    # exact); sampling time 0.9 s, as the paper's SEM at 720 ns/px.
    law = ControlLaw(dofs=("x", "y"))
    content = np.array([60.0, -25.0])
    pixel_nm = 177.0
    history = []
    for _ in range(40):
        step = law.step(content[0], content[1], 0.0, pixel_nm, sampling_time_s=0.9)
        moved_px = CameraToStage().content_move_px(step.move["x_um"], step.move["y_um"], pixel_nm)
        content = content + np.array(moved_px)
        history.append(content.copy())
    history = np.array(history)
    assert np.abs(history[-1]).max() < 0.01
    assert np.all(np.sign(history[:, 0]) >= 0) and np.all(np.sign(history[:, 1]) <= 0)  # never crosses


def test_the_gain_is_capped_for_slow_sampling():
    law = ControlLaw(dofs=("x",), gain=AdaptiveGain(scale=1, minimum=5, maximum=5))
    step = law.step(10.0, 0.0, 0.0, 100.0, sampling_time_s=4.0)
    assert step.gain == pytest.approx(NO_OVERSHOOT_GAIN_TIMES_T / 4.0)


def drifting_plant(law: ControlLaw, iterations: int, drift_px_per_s: float = 0.05, sampling_time_s: float = 1.4):
    """Content starts 3 px off and drifts; the stage moves what it is told."""
    content = np.array([3.0, -3.0])
    history = []
    for _ in range(iterations):
        step = law.step(content[0], content[1], 0.0, 42.46, sampling_time_s=sampling_time_s)
        moved_px = CameraToStage().content_move_px(step.move["x_um"], step.move["y_um"], 42.46)
        content = content + np.array(moved_px) + drift_px_per_s * sampling_time_s
        history.append(content.copy())
    return np.array(history)


def test_integral_action_removes_the_steady_error_drift_leaves_a_proportional_law():
    proportional = drifting_plant(ControlLaw(dofs=("x", "y")), 80)
    integral = drifting_plant(ControlLaw(dofs=("x", "y"), integral_time_s=10.0), 80)
    # Proportional: the error settles at drift / gain, about 0.1 px here (x5000, 1.4 s frames).
    assert np.abs(proportional[-10:]).min() > 0.08
    assert np.abs(integral[-10:]).max() < 0.01


def test_the_integral_does_not_wind_up_far_from_the_target():
    law = ControlLaw(dofs=("x", "y"), integral_time_s=10.0)
    law.step(40.0, -30.0, 0.0, 177.0, sampling_time_s=0.9)
    assert law.integral == pytest.approx([0.0, 0.0])
    for _ in range(200):
        law.step(1.5, 0.0, 0.0, 177.0, sampling_time_s=0.9)
    assert abs(law.integral[0]) <= law.integral_zone * law.integral_time_s
    law.reset()
    assert law.integral is None


def test_both_laws_return_one_frozen_law_step():
    planar = ControlLaw(dofs=("x", "y", "rotation"), integral_time_s=10.0).step(1.0, -2.0, 3.0, 100.0, 0.9)
    tilt = TiltLaw(("alpha", "beta")).step(1.0, -0.5, 2.0)
    for step in (planar, tilt):
        assert isinstance(step, LawStep)
        assert isinstance(step.error, tuple) and isinstance(step.velocity, tuple)
        with pytest.raises(AttributeError):
            step.gain = 1.0  # frozen
    assert set(planar.move) == {"x_um", "y_um", "rotation_deg"} and planar.integral == (0.0, 0.0, 0.0)
    assert set(tilt.move) == {"tilt_x_deg", "tilt_y_deg"} and tilt.integral is None
    assert planar.cost == pytest.approx(cost(np.array(planar.error)))
    idle = LawStep.idle()
    assert idle.move == {} and idle.cost == 0.0 and idle.error == () and idle.velocity == ()


def test_the_tilt_law_takes_its_signs_from_the_camera_to_stage_transform():
    plain = TiltLaw(("alpha", "beta")).step(1.0, -0.5, 2.0)
    flipped = TiltLaw(("alpha", "beta"), camera_to_stage=CameraToStage(tilt_signs=(-1, 1))).step(1.0, -0.5, 2.0)
    assert flipped.move["tilt_x_deg"] == pytest.approx(-plain.move["tilt_x_deg"])
    assert flipped.move["tilt_y_deg"] == pytest.approx(plain.move["tilt_y_deg"])
    assert plain.move["tilt_x_deg"] < 0 < plain.move["tilt_y_deg"]  # drives alpha = 1, beta = -0.5 to zero


@pytest.mark.parametrize("intervals", [(10.0, 10.0, 10.0, 10.0), (10.0, 80.0, 10.0, 40.0), (80.0, 10.0, 80.0, 10.0)])
def test_the_tilt_law_approaches_without_overshoot_whatever_the_intervals_between_sweeps(intervals):
    # A tilt plant that turns as told, sweeps at uneven intervals (one scanned during a
    # tilt move is skipped, so the next interval is twice as long): the error falls on
    # every sweep and never changes sign.
    law = TiltLaw(("alpha", "beta"))
    error = np.array([-0.96, -1.6])
    for interval in intervals:
        step = law.step(*error, interval)
        moved = np.array([step.move["tilt_x_deg"], step.move["tilt_y_deg"]])
        after = error + moved  # the default signs: a move of +1 degree adds 1 degree to the error
        assert np.all(np.abs(after) < np.abs(error)) and np.all(np.sign(after) == np.sign(error)), (interval, error, after)
        error = after


@pytest.mark.parametrize("start", [(7.0, -4.0), (-0.6, 0.3), (0.0, 2.5)])
def test_the_position_tilt_law_undoes_the_measured_tilt_in_one_move(start):
    # The same plant: what is left after one move is the theta-u vector's departure from
    # the angles themselves, second order in the tilt (under 2 % of it from 7 degrees).
    error = np.array(start)
    step = PositionTiltLaw(("alpha", "beta")).step(*error)
    after = error + np.array([step.move["tilt_x_deg"], step.move["tilt_y_deg"]])
    assert np.linalg.norm(after) <= 0.02 * np.linalg.norm(error) + 1e-9, (error, after)
    assert step.gain == 1.0 and step.velocity == () and step.cost == pytest.approx(cost(np.array(step.error)))
    flipped = PositionTiltLaw(("alpha", "beta"), CameraToStage(tilt_signs=(1, -1))).step(*error)
    assert flipped.move["tilt_x_deg"] == pytest.approx(step.move["tilt_x_deg"])
    assert flipped.move["tilt_y_deg"] == pytest.approx(-step.move["tilt_y_deg"])


def test_the_position_tilt_law_shrinks_a_step_its_measurement_cannot_tell_well_from_zero():
    law = PositionTiltLaw(("alpha", "beta"))
    far = law.step(6.0, -0.2, spread_deg={"alpha": 0.07, "beta": 0.1})
    assert far.move["tilt_x_deg"] == pytest.approx(-6.0 * (1 - (0.07 / 6.0) ** 2), rel=0.02)  # nearly whole
    assert far.move["tilt_y_deg"] == pytest.approx(0.2 * 0.75, rel=0.02)  # e = 2 sigma: three quarters
    within_noise = law.step(0.05, 0.0, spread_deg={"alpha": 0.07, "beta": 0.07})
    assert within_noise.move["tilt_x_deg"] == 0.0 and within_noise.move["tilt_y_deg"] == 0.0
    unknown = law.step(0.2, 0.0, spread_deg={"alpha": 0.0, "beta": 0.0})  # no standard error: taken as it is
    assert unknown.move["tilt_x_deg"] == pytest.approx(-0.2, rel=1e-3)


def test_each_planar_law_brings_its_tilt_law():
    from semservo.control import make_tilt_law

    assert isinstance(make_tilt_law("paper", ("alpha",)), TiltLaw)
    position = make_tilt_law("position", ("beta",))
    assert isinstance(position, PositionTiltLaw) and set(position.step(3.0, -1.0).move) == {"tilt_y_deg"}
    with pytest.raises(ValueError, match="unknown law"):
        make_tilt_law("bang-bang", ("alpha",))


# --------------------------------------------------------------------------------------
# The position law (not the paper's)

from semservo.control import (  # noqa: E402
    LAWS, PositionLaw, StageSettling, UnexpectedResponse, make_law, move_pieces, planar_limit_um, saturate_planar,
    settling_time_s,
)


def position_plant(law: PositionLaw, start_px, *, gain: float = 1.0, pixel_nm: float = 177.0, noise_px: float = 0.0,
                   drift_px_per_s: float = 0.0, frames: int = 30, frame_s: float = 0.46, seed: int = 0,
                   camera: CameraToStage = CameraToStage(), hold: bool = False, noise_of=None):
    """A stage that moves ``gain`` times the commanded move (the law's model unknown to
    it), frames every ``frame_s`` (a move makes the next frame stale: fresh ones every
    other), estimates with Gaussian noise (or ``noise_of(scan number)``, px). Returns the
    true errors after each step, the steps, and the step the law declared convergence at
    (None: never)."""
    rng = np.random.default_rng(seed)
    content = np.array(start_px, dtype=float)
    t, history, steps, converged_at = 0.0, [], [], None
    for index in range(frames):
        measured = content + rng.normal(0.0, noise_px, 2) if noise_px else content
        if noise_of is not None:
            measured = content + noise_of(int(round(t / frame_s)))
        step = law.step(measured[0], measured[1], 0.0, pixel_nm, frame_interval_s=(t, t + frame_s),
                        now_s=t + frame_s + 0.05)
        steps.append(step)
        if law.converged and converged_at is None:
            converged_at = index
            if not hold:
                break
        if step.move:
            moved = camera.content_move_px(step.move.get("x_um", 0.0), step.move.get("y_um", 0.0), pixel_nm)
            content = content + gain * np.array(moved)
            law.applied(step.move, at_s=t + frame_s + 0.05)
            t += frame_s  # the next scan is stale
        t += frame_s
        content = content + drift_px_per_s * frame_s
        history.append(content.copy())
    return np.array(history), steps, converged_at


@pytest.mark.parametrize("gain", [0.85, 1.0, 1.1])
def test_the_position_law_reaches_the_target_in_a_few_fresh_frames_on_a_modelled_stage(gain):
    law = PositionLaw(("x", "y"), noise_px=0.01)
    history, steps, converged_at = position_plant(law, (40.0, -25.0), gain=gain, noise_px=0.01)
    assert converged_at is not None and converged_at <= 4  # measure, two or three moves, confirm
    assert np.hypot(*history[-1]) <= 0.1


def test_the_position_law_with_an_unknown_model_converges_more_slowly_without_overshoot():
    for gain in (0.7, 1.3, 1.6):  # the stage moves 0.7-1.6 x what a nominal linear model says
        law = PositionLaw(("x", "y"), model_uncertainty=0.7, noise_px=0.01)
        history, _, converged_at = position_plant(law, (60.0, 20.0), gain=gain, noise_px=0.01)
        assert converged_at is not None and converged_at <= 8
        along = history @ np.array([60.0, 20.0]) / np.hypot(60.0, 20.0)
        assert along.min() >= -0.1, f"overshot by {-along.min():.2f} px at gain {gain}"


def test_the_position_law_respects_the_saturation_and_keeps_the_direction():
    law = PositionLaw(("x", "y"), max_move_um=10.0)
    step = law.step(300.0, -400.0, 0.0, 1000.0)  # 500 um away
    assert math.hypot(step.move["x_um"], step.move["y_um"]) == pytest.approx(10.0)
    assert step.move["x_um"] / step.move["y_um"] == pytest.approx(300.0 / -400.0)
    turning = PositionLaw(("rotation",), max_turn_deg=2.0)
    assert turning.step(0.0, 0.0, 30.0, 100.0).move["rotation_deg"] == pytest.approx(-2.0)


def test_the_position_law_chains_moves_only_once_the_stage_has_responded_as_commanded():
    """A first move, on a stage not yet seen to respond, stays within one command's
    limit; once a move has moved the content as commanded, a far target is one frame's
    work (``max_moves`` x ``max_move_um``); a stage moving the wrong way never unlocks it."""
    pixel_nm, camera = 177.0, CameraToStage()
    law = PositionLaw(("x", "y"), max_move_um=10.0, max_moves=3, noise_px=0.01)
    content = np.array([300.0, -20.0])  # 53 um away
    first = law.step(*content, 0.0, pixel_nm)
    assert math.hypot(first.move["x_um"], first.move["y_um"]) == pytest.approx(10.0)
    law.applied(first.move)
    content = content + np.array(camera.content_move_px(first.move["x_um"], first.move["y_um"], pixel_nm))
    chained = law.step(*content, 0.0, pixel_nm)
    assert math.hypot(chained.move["x_um"], chained.move["y_um"]) == pytest.approx(30.0)

    wrong = PositionLaw(("x", "y"), max_move_um=10.0, max_moves=3, noise_px=0.01)
    content = np.array([300.0, -20.0])
    first = wrong.step(*content, 0.0, pixel_nm)
    wrong.applied(first.move)
    content = content - np.array(camera.content_move_px(first.move["x_um"], first.move["y_um"], pixel_nm))
    held = wrong.step(*content, 0.0, pixel_nm)  # implausible: asked again, not moved
    assert not held.move
    again = wrong.step(*content, 0.0, pixel_nm)  # implausible again: it counts, and nothing is unlocked
    assert math.hypot(again.move["x_um"], again.move["y_um"]) <= 10.0 + 1e-9
    assert not wrong._responded


def test_saturation_keeps_the_direction_and_the_turn_and_only_the_position_law_chains():
    move, saturated = saturate_planar({"x_um": 30.0, "y_um": -40.0, "rotation_deg": 3.0}, 10.0)
    assert saturated and move == pytest.approx({"x_um": 6.0, "y_um": -8.0, "rotation_deg": 3.0})
    assert saturate_planar({"x_um": 3.0}, 10.0) == ({"x_um": 3.0}, False)
    assert planar_limit_um(PositionLaw(("x", "y")), 10.0, 3) == 30.0
    assert planar_limit_um(make_law("paper"), 10.0, 3) == 10.0


def test_a_move_is_made_in_equal_pieces_within_the_limit():
    pieces = move_pieces({"x_um": 18.0, "y_um": -24.0, "rotation_deg": 1.5}, 10.0)
    assert len(pieces) == 3
    assert all(math.hypot(piece["x_um"], piece["y_um"]) == pytest.approx(10.0) for piece in pieces)
    assert sum(piece["x_um"] for piece in pieces) == pytest.approx(18.0)
    assert sum(piece["y_um"] for piece in pieces) == pytest.approx(-24.0)
    assert pieces[0]["rotation_deg"] == 1.5 and all("rotation_deg" not in piece for piece in pieces[1:])
    assert move_pieces({"x_um": 10.0}, 10.0) == [{"x_um": 10.0}]  # at the limit: one piece
    assert move_pieces({"rotation_deg": 2.0}, 10.0) == [{"rotation_deg": 2.0}]


def creeping_plant(law: PositionLaw, start_px, *, creep_per_decade: float, gain: float = 1.05, pixel_nm: float = 177.0,
                   frame_s: float = 0.46, frames: int = 12, seed: int = 3):
    """A stage whose content goes on by ``creep_per_decade`` of the last move per decade
    of time after it (log10(1 + t / 0.1 s), the reference's "1-2 % of the last move per
    decade"), until the next move. Returns the true error (px) at the frame the law
    declared arrival, 10 s later, and that frame's index (None: never)."""
    rng = np.random.default_rng(seed)
    camera = CameraToStage()
    base, last_move, written_at, t = np.array(start_px, dtype=float), np.zeros(2), None, 0.0

    def content(at_s):
        if written_at is None:
            return base
        return base + last_move * creep_per_decade * math.log10(1 + max(at_s - written_at, 0.0) / 0.1)

    for index in range(frames):
        measured = content(t + frame_s / 2) + rng.normal(0.0, 0.01, 2)
        step = law.step(measured[0], measured[1], 0.0, pixel_nm, frame_interval_s=(t, t + frame_s),
                        now_s=t + frame_s + 0.05)
        if law.converged:
            return float(np.hypot(*content(t + frame_s))), float(np.hypot(*content(t + frame_s + 10.0))), index
        if step.move:
            at = t + frame_s + 0.05
            base = content(at)  # the move before stops creeping
            last_move = gain * np.array(camera.content_move_px(step.move.get("x_um", 0.0), step.move.get("y_um", 0.0),
                                                               pixel_nm))
            base, written_at = base + last_move, at
            law.applied(step.move, at_s=at)
            t += frame_s
        t += frame_s
    return float(np.hypot(*content(t))), float(np.hypot(*content(t + 10.0))), None


def test_the_position_law_follows_the_creep_of_its_last_move_and_arrives_where_it_stays():
    """Creep of 1.5 % of the last move per decade: the law predicts it, so it does not
    declare arrival where the creep carries the content beyond tolerance seconds later."""
    arrived, later, index = creeping_plant(PositionLaw(("x", "y"), noise_px=0.01), (50.0, -35.0),
                                           creep_per_decade=0.015)
    assert index is not None and index <= 5
    assert arrived <= 0.1 and later <= 0.1, (arrived, later)


@pytest.mark.parametrize("creep_per_decade", [0.015, 0.0])
def test_a_large_move_that_lands_within_tolerance_is_trimmed_before_its_creep_carries_it_out(creep_per_decade):
    """The frame after a 60 px move shows the target within tolerance; the move's creep
    (1.5 % of it per decade) will carry the content about 1 px on within 10 s: the law
    trims now instead of declaring arrival. Told there is no creep, it arrives."""
    law = PositionLaw(("x", "y"), noise_px=0.01, creep_per_decade=creep_per_decade)
    first = law.step(60.0, 0.0, 0.0, 177.0, frame_interval_s=(0.0, 0.46), now_s=0.51)
    law.applied(first.move, at_s=0.51)
    landed = law.step(0.03, 0.0, 0.0, 177.0, frame_interval_s=(0.92, 1.38), now_s=1.43)
    if creep_per_decade:
        assert not law.converged and landed.move and landed.move["x_um"] != 0.0
    else:
        assert law.converged and not landed.move


def test_the_position_law_never_acts_on_a_refused_or_stale_frame():
    law = PositionLaw(("x", "y"))
    assert law.step(50.0, 0.0, 0.0, 177.0, confident=False) == LawStep.idle()
    assert law.state is None  # nothing learned either
    first = law.step(50.0, 0.0, 0.0, 177.0)
    law.applied(first.move)
    # A wild estimate from a frame scanned while the move landed: ignored.
    assert law.step(-400.0, 300.0, 0.0, 177.0, fresh=False) == LawStep.idle()
    assert law.step(-400.0, 300.0, 0.0, 177.0, confident=False) == LawStep.idle()
    after = law.step(0.5, 0.0, 0.0, 177.0)
    assert abs(after.move.get("x_um", 0.0)) < 0.2  # acted on the fresh frame only


def test_a_stage_moving_the_wrong_way_stops_the_position_law():
    law = PositionLaw(("x", "y"))
    with pytest.raises(UnexpectedResponse, match="x/y"):
        position_plant(law, (40.0, 0.0), gain=-1.0)


def test_a_move_that_lands_late_is_asked_again_not_counted_against_the_stage():
    """The first fresh frame after a move still shows the old pose (the move landed after
    the frame's scan began: a loaded computer's emulated amplifier did that): the law
    holds and asks the next frame, which shows the move; it carries on, no error. A stage
    that never follows is still stopped, two frames later than without the second look."""
    asked = "held: the last move not seen yet (asked again on the next frame)"
    law = PositionLaw(("x", "y"), noise_px=0.01)
    first = law.step(40.0, -25.0, 0.0, 177.0)
    law.applied(first.move)
    late = law.step(40.0, -25.0, 0.0, 177.0)  # not there yet
    assert late.move == {} and late.held == asked
    moved = CameraToStage().content_move_px(first.move["x_um"], first.move["y_um"], 177.0)
    landed = law.step(40.0 + moved[0], -25.0 + moved[1], 0.0, 177.0)
    assert landed.held == "" and not law._implausible.get("x/y")
    blocked = PositionLaw(("x", "y"), noise_px=0.01)
    steps = []
    with pytest.raises(UnexpectedResponse):
        for _ in range(6):
            step = blocked.step(40.0, -25.0, 0.0, 177.0)
            steps.append(step.held or "moved")
            blocked.applied(step.move)
    assert steps == ["moved", asked, "moved", asked], steps


def test_the_position_law_holds_against_drift_and_does_not_chase_noise():
    law = PositionLaw(("x", "y"), noise_px=0.03)
    history, steps, converged_at = position_plant(law, (0.05, 0.0), noise_px=0.03, frames=1)
    assert converged_at == 0 and steps[0].move == {}  # within tolerance: nothing to do
    # Holding against drift of 0.05 px/s per axis (2 nm/s at x5000), estimates 0.03 px noisy.
    law = PositionLaw(("x", "y"), noise_px=0.03)
    history, steps, _ = position_plant(law, (0.0, 0.0), noise_px=0.03, drift_px_per_s=0.05, frames=200,
                                       pixel_nm=42.0, hold=True)
    assert np.hypot(*history.T).max() <= 0.11
    assert law.state[2:4] == pytest.approx([0.05, 0.05], abs=0.02)  # the drift, estimated
    # Without drift, noise alone: hardly a correction in 200 frames.
    law = PositionLaw(("x", "y"), noise_px=0.03)
    history, steps, _ = position_plant(law, (0.0, 0.0), noise_px=0.03, frames=200, pixel_nm=42.0, hold=True)
    assert sum(1 for step in steps if step.move) <= 5


def alternating_noise(amplitude_px: float, seed: int = 3):
    """An estimate's noise like x5000's vibration aliased by the frame: each frame off by
    nearly the opposite of the last, the amplitude wandering slowly, a little white noise."""
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 2 * np.pi, 2)
    return lambda scan: (amplitude_px * (-1) ** scan * np.cos(2 * np.pi * 0.04 * scan + phase)
                         + rng.normal(0.0, 0.01, 2))


def test_the_position_law_learns_that_consecutive_frames_noise_alternates_and_averages_it_away():
    # Frames at rest 0.04 px from the target, each up to 0.15 px off the opposite way to
    # the last; the prior noise is what a teach measures of one frame.
    arrived = {}
    for floor in (-0.9, 0.0):  # 0: the noise taken as white
        arrivals = []
        for seed in range(5):
            law = PositionLaw(("x", "y"), noise_px=0.12, noise_correlation_floor=floor)
            history, steps, converged_at = position_plant(law, (0.03, -0.02), frames=40, pixel_nm=42.0,
                                                          noise_of=alternating_noise(0.15, seed))
            arrivals.append(converged_at if converged_at is not None else 99)
            assert np.hypot(*history[-1]) <= 0.1
        arrived[floor] = arrivals
    assert max(arrived[-0.9]) <= 8, arrived  # seen: 2-7 frames
    assert np.median(arrived[0.0]) >= 2 * np.median(arrived[-0.9]), arrived  # seen: 14 against 3
    # Held longer, the law learns the correlation itself: -0.9 or near (shrunk a little
    # towards 0 by the prior's weight).
    law = PositionLaw(("x", "y"), noise_px=0.12)
    position_plant(law, (0.03, -0.02), frames=40, pixel_nm=42.0, noise_of=alternating_noise(0.15), hold=True)
    assert law.noise_model()[1] == pytest.approx([-0.85, -0.85], abs=0.1)


def test_the_position_law_takes_white_noise_and_drift_as_uncorrelated_noise():
    for noise_px in (0.03, 0.06):  # as the prior says, and twice it
        for seed in range(3):
            law = PositionLaw(("x", "y"), noise_px=0.03)
            position_plant(law, (0.0, 0.0), noise_px=noise_px, frames=150, pixel_nm=42.0, hold=True, seed=seed)
            sigma, phi = law.noise_model()
            assert sigma == pytest.approx([noise_px, noise_px], rel=0.25) and phi[0] > -0.25, (noise_px, seed, phi)
    law = PositionLaw(("x", "y"), noise_px=0.01)
    position_plant(law, (0.0, 0.0), noise_px=0.005, drift_px_per_s=0.05, frames=150, pixel_nm=42.0, hold=True)
    assert law.noise_model()[1] == pytest.approx([0.0, 0.0])  # a drift's positive correlation is not noise's


def test_frames_known_only_by_their_acquisition_time_learn_the_noise_from_their_spacing():
    # An interval of no length (a watched folder's file: its time only): the period is the
    # spacing of the frames, so the lags are still told apart.
    def frames(law, noise_of, count=60):
        for index in range(count):
            t = 100.0 + 0.5 * index
            measured = np.array([0.02, -0.01]) + noise_of(index)
            law.step(measured[0], measured[1], 0.0, 42.0, frame_interval_s=(t, t), now_s=t + 0.05)

    alternating = PositionLaw(("x", "y"), noise_px=0.12)
    frames(alternating, alternating_noise(0.15))
    assert alternating.noise_model()[1][0] < -0.6
    rng = np.random.default_rng(5)
    white = PositionLaw(("x", "y"), noise_px=0.03)
    frames(white, lambda index: rng.normal(0.0, 0.06, 2))
    assert white.noise_model()[1][0] > -0.25


def test_a_view_moved_by_a_tilt_keeps_the_drift_learned_and_starts_the_position_afresh():
    # Hold against drift long enough to learn it, then the view jumps (a tilt about the
    # cradle's pivot): the position restarts from the next frame, the drift does not.
    law = PositionLaw(("x", "y"), noise_px=0.03)
    position_plant(law, (0.0, 0.0), noise_px=0.03, drift_px_per_s=0.05, frames=120, pixel_nm=42.0, hold=True)
    drift, drift_covariance = law.state[2:4].copy(), law.covariance[2:4, 2:4].copy()
    gains = law.state[4:6].copy()
    assert drift == pytest.approx([0.05, 0.05], abs=0.02)
    law.view_moved()
    assert law.state is None and not law.converged
    law.step(3.0, -2.0, 0.0, 42.0, frame_interval_s=(1000.0, 1000.46), now_s=1000.5)
    assert law.state[:2] == pytest.approx([3.0, -2.0], abs=0.05)  # the new view's error, from its frame
    assert law.state[2:4] == pytest.approx(drift, abs=1e-6)  # the sample's drift, as learned
    assert law.covariance[2:4, 2:4] == pytest.approx(drift_covariance, rel=1e-3, abs=1e-12)
    assert law.state[4:6] == pytest.approx(gains)
    # A second tilt before any frame (no state): what was kept stays kept.
    law.reset()
    law.step(3.0, -2.0, 0.0, 42.0, frame_interval_s=(1000.0, 1000.46), now_s=1000.5)
    law.state[4:6] = kept = np.array([0.8, 1.2])  # gains as if learned
    law.view_moved()
    law.view_moved()
    law.step(1.0, 1.0, 0.0, 42.0, frame_interval_s=(1002.0, 1002.46), now_s=1002.5)
    assert law.state[4:6] == pytest.approx(kept)
    # Another magnification (the position in other pixels) forgets the drift too.
    law.step(3.0, -2.0, 0.0, 84.0, frame_interval_s=(1003.0, 1003.46), now_s=1003.5)
    assert law.state[2:4] == pytest.approx([0.0, 0.0])


def test_the_position_law_trims_a_clear_residue_at_the_tolerance_edge_before_it_declares_arrival():
    """0.09 px off, seen clearly (estimates 0.005 px noisy): within the 0.1 px tolerance,
    but a bias of the estimate or the next creep would put the stage beyond it; the law
    trims it first, then arrives near the centre. Under noise as large as the residue it
    does not chase it (arrives at once)."""
    law = PositionLaw(("x", "y"), noise_px=0.005)
    history, steps, converged_at = position_plant(law, (0.09, 0.0), noise_px=0.005, pixel_nm=177.0)
    assert steps[0].move and converged_at == 1  # trimmed, then arrived on the next fresh frame
    assert np.hypot(*history[-1]) <= 0.05
    noisy = PositionLaw(("x", "y"), noise_px=0.06)
    _, steps, converged_at = position_plant(noisy, (0.03, 0.0), noise_px=0.0, pixel_nm=42.0)
    assert converged_at == 0 and steps[0].move == {}


def test_settling_follows_a_first_order_model():
    assert settling_time_s(10.0, 0.003, 0.001) == pytest.approx(0.003 * math.log(1e4))
    assert settling_time_s(0.0005, 0.003, 0.001) == 0.0
    settling = StageSettling()
    assert settling.after_s({"x_um": 0.03, "y_um": -10.0}) == pytest.approx(settling_time_s(10.0, 0.003, 0.001))
    assert settling.after_s({}) == 0.0
    with pytest.raises(ValueError):
        settling_time_s(1.0, 0.003, 0.0)


def test_laws_are_picked_by_name():
    assert LAWS == ("paper", "position")
    assert isinstance(make_law("paper", ("x", "y")), ControlLaw)
    assert isinstance(make_law("position", ("x", "y", "rotation")), PositionLaw)
    with pytest.raises(ValueError, match="unknown law"):
        make_law("fast")
    # One call for either law: the paper's takes the position law's keywords too.
    for name in LAWS:
        law = make_law(name, ("x", "y"))
        assert law.step(5.0, 0.0, 0.0, 177.0, 0.9, fresh=False) == LawStep.idle()
        assert law.step(5.0, 0.0, 0.0, 177.0, 0.9, confident=False) == LawStep.idle()
        step = law.step(5.0, 0.0, 0.0, 177.0, 0.9, frame_interval_s=(0.0, 0.45), now_s=0.5)
        assert step.move["x_um"] < 0  # drives the content back
        law.applied(step.move, at_s=0.5)
    with pytest.raises(ValueError, match="drives"):
        PositionLaw(("x", "alpha"))


def test_a_rotation_only_position_law_holds_still_without_learning_a_planar_noise(recwarn):
    # It used to average an empty planar error at rest ("mean of empty slice").
    law = PositionLaw(("rotation",), noise_deg=0.002)
    for frame in range(6):
        step = law.step(0.0, 0.0, 0.001, 70.0, frame_interval_s=(frame * 0.6, frame * 0.6 + 0.36))
    assert step.move == {} and law.converged
    assert np.isfinite(law.noise_model()[0]).all()
    assert not [warning for warning in recwarn if issubclass(warning.category, RuntimeWarning)]


def test_the_position_law_turns_the_rotation_too():
    law = PositionLaw(("x", "y", "rotation"), noise_px=0.01, noise_deg=0.002)
    camera = CameraToStage(axis_signs=(1, -1), orientation_deg=20.0, rotation_sign=-1)
    law.camera_to_stage = camera
    content, rotation, t = np.array([30.0, 12.0]), 2.0, 0.0
    for index in range(8):
        step = law.step(content[0], content[1], rotation, 177.0, frame_interval_s=(t, t + 0.46))
        if law.converged:
            break
        moved = camera.content_move_px(step.move.get("x_um", 0.0), step.move.get("y_um", 0.0), 177.0)
        content = content + 0.9 * np.array(moved)  # the stage makes 90 % of each move
        rotation += 0.9 * step.move.get("rotation_deg", 0.0) * camera.rotation_sign
        law.applied(step.move, at_s=t + 0.5)
        t += 0.92
    assert law.converged and index <= 5
    assert np.hypot(*content) <= 0.1 and abs(rotation) <= 0.05
