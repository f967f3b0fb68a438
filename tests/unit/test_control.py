"""The control law (eq. 30-37) as pure functions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semservo.control import (
    NO_OVERSHOOT_GAIN_TIMES_T, AdaptiveGain, CameraToStage, ControlLaw, ExponentialGain, LawStep, TiltLaw, cost,
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
