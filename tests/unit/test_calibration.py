"""The pure parts of stage calibration: the sweep, the branch fit, the loop width."""

from __future__ import annotations

import numpy as np
import pytest

from semservo.calibration import SweepPoint, fit_branches, fit_residual_um, loop_width, sweep_voltages
from semservo.simulation.piezo import TRITOR_POLYNOMIALS


def test_sweep_goes_up_then_back_down_with_directions():
    sweep = sweep_voltages(-10.0, 10.0, 5.0)
    assert sweep == [(-10.0, 1), (-5.0, 1), (0.0, 1), (5.0, 1), (10.0, 1),
                     (5.0, -1), (0.0, -1), (-5.0, -1), (-10.0, -1)]
    # A step that does not divide the range is shrunk so both ends are visited.
    assert [v for v, _ in sweep_voltages(0.0, 10.0, 4.0)][:4] == pytest.approx([0, 10 / 3, 20 / 3, 10])


@pytest.mark.parametrize("low, high, step", [(5, 5, 1), (10, 0, 1), (0, 10, 0), (0, 10, 11)])
def test_sweep_refuses_a_range_it_cannot_walk(low, high, step):
    with pytest.raises(ValueError):
        sweep_voltages(low, high, step)


def points_on(rising_of_v, falling_of_v, low=-19.0, high=96.0, step=2.5) -> list[SweepPoint]:
    return [SweepPoint(v, d, (rising_of_v if d > 0 else falling_of_v)(v), 0.0, 1.0, i)
            for i, (v, d) in enumerate(sweep_voltages(low, high, step))]


def inverse(polynomial):
    """d(V) of a monotonic V = p(d) by dense interpolation."""
    displacements = np.linspace(-5, 110, 20001)
    voltages = np.polyval(polynomial, displacements)
    return lambda v: float(np.interp(v, voltages, displacements))


def test_fit_recovers_the_lab_polynomials_from_exact_points():
    increasing, decreasing = TRITOR_POLYNOMIALS[("x", "increasing")], TRITOR_POLYNOMIALS[("x", "decreasing")]
    points = points_on(inverse(increasing), inverse(decreasing))
    model = fit_branches(points)
    d = np.linspace(5, 95, 50)
    assert np.abs(np.polyval(model.increasing, d) - np.polyval(increasing, d)).max() < 0.05  # volts
    # The lab's two polynomials are separate fits that do not meet at the top (96 V);
    # a measured loop does, and the fit takes the turning point as the falling branch's
    # start, so that branch is recovered to within the mismatch.
    assert np.abs(np.polyval(model.decreasing, d) - np.polyval(decreasing, d)).max() < 1.0
    assert fit_residual_um(model, points) < 0.3


def test_loop_width_is_the_largest_gap_over_the_stroke():
    points = points_on(lambda v: v + 19.0, lambda v: v + 19.0 + 10.0 * np.sin(np.pi * (v + 19) / 115))
    assert loop_width(points) == pytest.approx(10.0 / 115.0, rel=0.01)


def test_loop_width_of_a_stage_that_did_not_move_is_an_error():
    with pytest.raises(ValueError, match="did not move"):
        loop_width(points_on(lambda v: 0.0, lambda v: 0.0))


def test_fit_needs_enough_points_per_branch():
    with pytest.raises(ValueError, match="more than 4 points"):
        fit_branches(points_on(lambda v: v, lambda v: v, 0.0, 10.0, 5.0))


def test_a_fit_the_frames_did_not_measure_is_no_model_and_partial_truth_is_none():
    """A watched folder's frames that lagged their moves read displacements that no loop
    explains (87 um of residual over a 6.7 um stroke, and the model was written); and
    frames the simulator cannot time give no truth, which the result must not half-use."""
    from semservo.calibration import Calibrator

    increasing, decreasing = TRITOR_POLYNOMIALS[("x", "increasing")], TRITOR_POLYNOMIALS[("x", "decreasing")]
    calibrator = Calibrator(stage=None, next_frame=None)
    good = calibrator.result(points_on(inverse(increasing), inverse(decreasing)))
    assert good.fit_problem() is None and good.true_loop_width is None
    scrambled = np.random.default_rng(3).permutation([p.displacement_um for p in points_on(
        inverse(increasing), inverse(decreasing))])
    lagged = [SweepPoint(p.voltage, p.direction, float(d), 0.0, 1.0, p.frame_seq, None if i % 2 else 1.0)
              for i, (p, d) in enumerate(zip(points_on(inverse(increasing), inverse(decreasing)), scrambled))]
    bad = calibrator.result(lagged)
    assert "the frames did not measure the steps" in bad.fit_problem()
    assert bad.true_loop_width is None and bad.true_error_um is None
