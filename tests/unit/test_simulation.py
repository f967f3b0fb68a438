"""The simulated lab's physics: what the issue asks the fake hardware to show."""

from __future__ import annotations

import time

import numpy as np
import pytest

from semservo.config import pixel_size_nm
from semservo.estimation import MotionEstimator
from semservo.simulation.piezo import PiezoAxis, voltage_for
from semservo.simulation.goniometer import BACKLASH_DEG
from semservo.simulation.sem import SEM, Pose, ScanSettings
from semservo.simulation.world import PRESETS, World

STILL = [Pose()] * 512


@pytest.fixture(scope="module")
def sem() -> SEM:
    return SEM("micropart", seed=7)


def render(sem: SEM, settings: ScanSettings, pose: Pose = Pose(), seed: int = 0) -> np.ndarray:
    return sem.render(settings, [pose] * settings.rows, [pose] * settings.rows, np.random.default_rng(seed))


def test_snr_grows_as_the_square_root_of_dwell(sem):
    """Noise measured directly: two frames of the same pose differ only by noise."""
    ratios = {}
    for dwell in (180.0, 720.0, 2880.0):
        settings = ScanSettings(dwell_ns=dwell, bit_depth=16)
        first = render(sem, settings, seed=1).astype(np.float64)
        second = render(sem, settings, seed=2).astype(np.float64)
        noise = np.std(first - second) / np.sqrt(2)
        ratios[dwell] = first.mean() / noise
    assert ratios[720.0] / ratios[180.0] == pytest.approx(2.0, rel=0.12)
    assert ratios[2880.0] / ratios[720.0] == pytest.approx(2.0, rel=0.12)


def test_a_frame_at_pose_p_is_the_reference_shifted_by_p_over_P(sem):
    settings = ScanSettings(dwell_ns=720.0, magnification=1200.0)
    pixel_um = pixel_size_nm(1200.0) / 1000
    reference = render(sem, settings, seed=3)
    estimator = MotionEstimator(reference, rotation=False, precision="full")
    for x_um, y_um in ((1.0, 0.0), (-2.3, 1.7), (4.0, -5.5)):
        motion = estimator.estimate(render(sem, settings, Pose(x_um=x_um, y_um=y_um), seed=4))
        assert motion.dx == pytest.approx(x_um / pixel_um, abs=0.05)
        assert motion.dy == pytest.approx(y_um / pixel_um, abs=0.05)


def test_the_rotation_stage_turns_the_content(sem):
    settings = ScanSettings()
    reference = render(sem, settings, seed=5)
    motion = MotionEstimator(reference).estimate(render(sem, settings, Pose(rotation_deg=3.0), seed=6))
    assert motion.rotation_deg == pytest.approx(3.0, abs=0.05)


def test_a_stage_move_during_the_scan_shears_the_frame(sem):
    settings = ScanSettings(dwell_ns=720.0)
    pixel_um = settings.pixel_um
    still = render(sem, settings, seed=7)
    # The stage moves 6 um to the right while the frame is scanned, steadily.
    start = [Pose(x_um=6.0 * row / 512) for row in range(512)]
    end = [Pose(x_um=6.0 * (row + 1) / 512) for row in range(512)]
    moving = sem.render(settings, start, end, np.random.default_rng(8))
    top = MotionEstimator(still[:128], rotation=False).estimate(moving[:128])
    bottom = MotionEstimator(still[-128:], rotation=False).estimate(moving[-128:])
    # Early lines saw almost no motion, late lines almost all of it: a shear. Each strip's
    # estimate lies within the motion its own lines saw (the bottom strip's lines moved
    # 4.5 to 6 um, 25 to 34 px: a single shift cannot say more about a sheared strip).
    assert top.dx == pytest.approx(0.75 / pixel_um, abs=1.0)
    assert 4.5 / pixel_um <= bottom.dx <= 6.0 / pixel_um


def sharpness(image: np.ndarray) -> float:
    """Normalized variance of the gradient: falls as the image blurs."""
    image = image.astype(np.float64)
    gradient = np.diff(image, axis=1)[:-1, :] ** 2 + np.diff(image, axis=0)[:, :-1] ** 2
    return float(gradient.mean() / image.var())


def test_defocus_blur_grows_with_height_offset_and_recovers_in_focus():
    sem = SEM("gold-on-carbon", seed=3)
    settings = ScanSettings(dwell_ns=5800.0, magnification=5000.0, working_distance_um=-0.2)
    in_focus = sharpness(render(sem, settings, Pose(z_um=0.0)))
    values = [sharpness(render(sem, settings, Pose(z_um=z))) for z in (10.0, 25.0, 60.0)]
    assert in_focus > values[0] > values[1] > values[2]
    assert sharpness(render(sem, settings, Pose(z_um=0.0), seed=9)) == pytest.approx(in_focus, rel=0.05)


def test_tilt_defocuses_the_field_away_from_the_tilt_axis():
    # The paper's tilt estimation assumes a depth of field under 300 nm: a wide beam.
    # Tilted about axes through the surface (no pivot lever), so the centre stays in focus.
    sem = SEM("gold-on-carbon", seed=3, beam_half_angle=0.1, pivot_depth_um=0.0)
    settings = ScanSettings(dwell_ns=5800.0, magnification=5000.0, working_distance_um=-0.2)
    tilted = render(sem, settings, Pose(tilt_y_deg=30.0))
    flat = render(sem, settings)
    # Tilted about the field's centre: focused there, one edge above focus, one below.
    centre, left, right = tilted[:, 206:306], tilted[:, :100], tilted[:, -100:]
    assert sharpness(centre) > 1.5 * max(sharpness(left), sharpness(right))
    assert sharpness(flat[:, :100]) > 1.5 * sharpness(left)  # untilted, the edge is sharp


def loop_width(axis: PiezoAxis, low: float, high: float) -> tuple[float, float]:
    voltages = np.linspace(low, high, 200)
    for _ in range(2):
        rising = np.array([axis.hysteresis.apply(v) for v in voltages])
        falling = np.array([axis.hysteresis.apply(v) for v in voltages[::-1]])[::-1]
    return float((falling - rising).max()), float(rising.max() - rising.min())


@pytest.mark.parametrize("name", ["x", "y"])
def test_hysteresis_loop_at_full_stroke_is_10_to_15_percent(name):
    width, stroke = loop_width(PiezoAxis(name), -19.0, 96.0)
    assert 95 < stroke < 105
    assert 0.10 <= width / stroke <= 0.15


@pytest.mark.parametrize("name", ["x", "y"])
def test_small_moves_show_small_loops_and_the_branches_follow_the_lab_model(name):
    axis = PiezoAxis(name)
    axis.hysteresis.apply(35.0)
    width, move = loop_width(axis, 35.0, 40.0)
    assert width / move < 0.04
    # On a long rising excursion the displacement follows the lab's increasing branch.
    axis = PiezoAxis(name)
    for voltage in np.linspace(-19, 96, 120):
        axis.hysteresis.apply(voltage)
    for target in (30.0, 60.0):
        rising_voltage = voltage_for(name, "increasing", target)
        axis2 = PiezoAxis(name)
        for voltage in np.linspace(-19, rising_voltage, 120):
            axis2.hysteresis.apply(voltage)
        assert axis2.hysteresis.displacement == pytest.approx(target, abs=6.5)  # within a few % of stroke


def test_piezo_settles_and_creeps_after_a_step():
    axis = PiezoAxis("x")
    axis.command(20.0, 0.0)
    start = axis.position(1.0)
    axis.command(40.0, 1.0)
    target = axis.hysteresis.displacement
    assert axis.position(1.0) == pytest.approx(start, abs=1e-3)  # no jump at the step
    assert axis.position(1.0 + 5 * axis.settle_s) == pytest.approx(target, rel=0.03)
    assert axis.position(100.0) > axis.position(1.1) > target * 0.99  # creep: slowly further


def test_presets_cover_the_papers_conditions():
    assert set(PRESETS) == {"optimal", "noisy", "high-magnification", "unstable", "high-quality-reference",
                            "mask-reference", "repeated-pattern", "tilts"}
    # The tilt regime: a small depth of field (2 P / alpha) of a few micrometres.
    from semservo.simulation.sem import beam_half_angle
    tilts = PRESETS["tilts"]
    depth_of_field = 2 * pixel_size_nm(tilts.magnification, 512) / 1000 / beam_half_angle(tilts.aperture_um,
                                                                                          tilts.working_distance_mm)
    assert 2 < depth_of_field < 5
    assert (PRESETS["optimal"].dwell_ns, PRESETS["optimal"].magnification) == (720, 1200)
    assert PRESETS["noisy"].dwell_ns == 180
    assert (PRESETS["high-magnification"].magnification, PRESETS["high-magnification"].dwell_ns) == (5000, 360)
    assert PRESETS["high-quality-reference"].reference_dwell_ns == 5800
    assert PRESETS["repeated-pattern"].scene == "chessboard" and PRESETS["repeated-pattern"].dwell_ns == 180


def test_the_world_scan_sees_stage_commands_and_the_true_pose():
    world = World(PRESETS["optimal"], speedup=1000.0)
    settings = ScanSettings(dwell_ns=180.0)
    reference, reference_start, reference_end = world.scan(settings)
    taught = world.pose((reference_start + reference_end) / 2)  # drift moves the home pose too
    world.set_voltage(0, 45.0)
    world.set_voltage(1, 31.0)
    import time

    time.sleep(0.05)  # 50 simulated seconds (more on a busy machine): settled, a little creep and drift
    moved, start, end = world.scan(settings)
    pose = world.pose((start + end) / 2)  # creep goes on during the scan
    motion = MotionEstimator(reference, rotation=False).estimate(moved)
    pixel_um = settings.pixel_um
    assert pose.x_um - taught.x_um > 2 and pose.y_um - taught.y_um < -2
    assert motion.dx == pytest.approx((pose.x_um - taught.x_um) / pixel_um, abs=0.5)
    assert motion.dy == pytest.approx((pose.y_um - taught.y_um) / pixel_um, abs=0.5)


def test_unstable_preset_changes_levels_over_time():
    world = World(PRESETS["unstable"], speedup=1.0)
    settings = ScanSettings()
    contrasts = {round(world.levels(t, settings).contrast, 3) for t in (0.0, 2.0, 4.0, 6.0)}
    assert len(contrasts) == 4


def test_the_rotation_stage_refuses_nan_and_what_is_beyond_its_travel():
    world = World(speedup=10.0)
    for bad in (float("nan"), float("inf"), 1e308, 400.0):
        with pytest.raises(ValueError, match="rotation_deg"):
            world.set_rotation_stage(rotation_deg=bad)
    with pytest.raises(ValueError, match="tilt_x_deg"):
        world.set_rotation_stage(rotation_deg=10.0, tilt_x_deg=float("nan"))
    assert world.rotation_stage["rotation_deg"] == 0.0, "refused whole: nothing changed"
    assert world.goniometer.targets()["tilt_x_deg"] == 0.0
    world.set_rotation_stage(rotation_deg=12.5)
    # It gets there at its own speed (10 degrees per simulated second).
    assert world.pose(world.now() + 2.0).rotation_deg == pytest.approx(12.5 - BACKLASH_DEG["rotation_deg"] / 2)


def test_a_failed_render_does_not_stop_simulated_time(monkeypatch):
    """A render that raised once left a sped-up world's clock standing still for good."""
    world = World(speedup=10.0)

    def broken(*_args, **_kwargs):
        raise FloatingPointError("a broken render")

    monkeypatch.setattr(world.sem, "render", broken)
    with pytest.raises(FloatingPointError):
        world.scan(ScanSettings(dwell_ns=100), wait=False)
    before = world.now()
    time.sleep(0.05)
    assert world.now() > before
