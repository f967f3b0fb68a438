"""The simulated lab's tilt physics: the goniometer's speed and backlash, the tilted
view's foreshortening and pivot lever, and depth from focus on its focus sweeps."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from semservo.simulation.goniometer import Goniometer
from semservo.simulation.sem import SEM, Pose, ScanSettings
from semservo.simulation.world import PRESETS, World
from semservo.estimation.tilt import estimate_tilt, plan_sweep


def test_each_axis_moves_at_its_speed_and_halts_where_it_is():
    stage = Goniometer(backlash={"rotation_deg": 0.0, "tilt_x_deg": 0.0, "tilt_y_deg": 0.0})
    stage.command(0.0, tilt_x_deg=4.0, rotation_deg=10.0)
    assert stage.angles(0.5) == pytest.approx({"rotation_deg": 5.0, "tilt_x_deg": 2.0, "tilt_y_deg": 0.0})
    assert stage.arrival() == pytest.approx(1.0)
    stage.halt(0.25)
    assert stage.angles(5.0)["tilt_x_deg"] == pytest.approx(1.0), "halted where it was"


def test_backlash_loses_the_play_on_a_reversal():
    stage = Goniometer(backlash={"rotation_deg": 0.02, "tilt_x_deg": 0.02, "tilt_y_deg": 0.02})
    stage.command(0.0, tilt_y_deg=2.0)
    up = stage.angles(10.0)["tilt_y_deg"]
    stage.command(10.0, tilt_y_deg=1.0)
    down = stage.angles(20.0)["tilt_y_deg"]
    assert up == pytest.approx(2.0 - 0.01) and down == pytest.approx(1.0 + 0.01)
    stage.command(20.0, tilt_y_deg=1.005)  # less than the play: the output does not move
    assert stage.angles(30.0)["tilt_y_deg"] == pytest.approx(down)


def test_the_stage_refuses_bad_targets_whole():
    stage = Goniometer()
    for bad in ({"tilt_x_deg": float("nan")}, {"tilt_y_deg": 46.0}, {"spin": 1.0}):
        with pytest.raises(ValueError):
            stage.command(0.0, rotation_deg=5.0, **bad)
    assert stage.targets() == {"rotation_deg": 0.0, "tilt_x_deg": 0.0, "tilt_y_deg": 0.0}


def frame(sem: SEM, pose: Pose, settings: ScanSettings, seed: int = 1) -> np.ndarray:
    return sem.render(settings, [pose] * settings.rows, [pose] * settings.rows, np.random.default_rng(seed))


def correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Over the middle of the field (the resampled view has no data near one edge)."""
    a, b = a.astype(np.float64)[128:-128, 128:-128], b.astype(np.float64)[128:-128, 128:-128]
    return float(np.corrcoef(a.ravel(), b.ravel())[0, 1])


def resampled(flat: np.ndarray, axis: str, degrees: float, lever_px: float) -> np.ndarray:
    """The untilted frame resampled as the tilt should show it: the pixel at centred
    offset r along the tilted axis shows the surface at (r + lever sin t) / cos t."""
    size = flat.shape[0]
    centred = np.arange(size, dtype=np.float32) - (size - 1) / 2
    angle = np.radians(degrees)
    source = (centred + lever_px * np.sin(angle)) / np.cos(angle) + (size - 1) / 2
    grid_y, grid_x = np.meshgrid(np.arange(size, dtype=np.float32), np.arange(size, dtype=np.float32), indexing="ij")
    if axis == "tilt_x_deg":  # about x: rows are foreshortened (a positive alpha's lever runs the other way)
        source = (centred - lever_px * np.sin(angle)) / np.cos(angle) + (size - 1) / 2
        grid_y = np.broadcast_to(source[:, None], flat.shape).astype(np.float32)
    else:
        grid_x = np.broadcast_to(source[None, :], flat.shape).astype(np.float32)
    return cv2.remap(flat.astype(np.float32), grid_x, grid_y, cv2.INTER_CUBIC)


# A sharp view everywhere (a tiny beam angle), so the geometry alone is measured.
GEOMETRY = ScanSettings(dwell_ns=2000.0, magnification=3000.0, working_distance_um=0.0)


@pytest.mark.parametrize("axis", ["tilt_x_deg", "tilt_y_deg"])
@pytest.mark.parametrize("pivot_um", [0.0, 20.0])
def test_a_tilted_view_is_foreshortened_by_the_cosine_and_shifted_by_the_pivot(axis, pivot_um):
    sem = SEM("gold-on-carbon", seed=3, beam_half_angle=1e-4, pivot_depth_um=pivot_um)
    flat, tilted = frame(sem, Pose(), GEOMETRY), frame(sem, Pose(**{axis: 20.0}), GEOMETRY)
    expected = resampled(flat, axis, 20.0, pivot_um / GEOMETRY.pixel_um)
    matched = correlation(tilted, expected)
    assert matched > 0.9
    # Neither an untilted view nor one with the lever the wrong way matches as well.
    assert correlation(tilted, flat) < matched - 0.2
    wrong_lever = resampled(flat, axis, 20.0, -pivot_um / GEOMETRY.pixel_um)
    if pivot_um:
        assert correlation(tilted, wrong_lever) < matched - 0.2


@pytest.mark.parametrize("alpha, beta", [(3.0, -2.0), (-8.0, 8.0), (0.5, 0.5), (15.0, -15.0)])
def test_depth_from_focus_recovers_the_simulated_tilts(alpha, beta):
    world = World(PRESETS["tilts"], speedup=1000.0)
    settings = ScanSettings(dwell_ns=360.0, magnification=PRESETS["tilts"].magnification)
    reference_sweep = plan_sweep(0.0, 3.5, 512 * settings.pixel_um)
    flat = np.stack([frame(world.sem, Pose(), replace(settings, working_distance_um=w), seed=i)
                     for i, w in enumerate(reference_sweep)])
    pose = Pose(tilt_x_deg=alpha, tilt_y_deg=beta)
    tilted = np.stack([frame(world.sem, pose, replace(settings, working_distance_um=w), seed=i)
                       for i, w in enumerate(reference_sweep)])
    taught = estimate_tilt(flat, reference_sweep, settings.pixel_um)
    measured = estimate_tilt(tilted, reference_sweep, settings.pixel_um)
    assert measured.confidence > 0.5
    assert measured.alpha_deg - taught.alpha_deg == pytest.approx(alpha, abs=0.15)
    assert measured.beta_deg - taught.beta_deg == pytest.approx(beta, abs=0.15)


def test_the_aperture_sets_the_depth_of_field():
    # A smaller aperture: a smaller beam half-angle, a deeper depth of field, so the same
    # distance from focus blurs less.
    world = World(PRESETS["tilts"], speedup=1000.0)
    settings = ScanSettings(dwell_ns=2000.0, magnification=3000.0, working_distance_um=6.0)
    sharp = ScanSettings(dwell_ns=2000.0, magnification=3000.0, working_distance_um=0.0)

    def sharpness(image):
        image = image.astype(np.float64)
        return float((np.diff(image, axis=1) ** 2).mean() / image.var())

    in_focus = sharpness(frame(world.sem, Pose(), sharp))
    wide = sharpness(frame(world.sem, Pose(), settings))  # the preset's 400 um aperture
    narrow = sharpness(frame(world.sem, Pose(), replace(settings, aperture_um=50.0)))
    assert wide < narrow <= in_focus * 1.05
    assert world.sem.half_angle(replace(settings, aperture_um=50.0)) == pytest.approx(0.005, rel=0.01)


@pytest.mark.parametrize("depth_of_field_um", [None, 3.5])
def test_a_teach_with_tilts_on_a_deep_depth_of_field_is_refused_with_the_reason(depth_of_field_um):
    """The ``optimal`` preset (x1200, the default aperture at 10 mm: a depth of field of
    ~49 um over a 91 um field): a tilt of a few degrees moves the focus across the field
    by a fraction of a depth of field, which focus cannot place. The estimator service's
    sweep, planned with that depth of field or with the setting's default 3.5 um (a
    user who did not change it), is refused with the reason, so a 5-DOF run there has
    no taught sweep and cannot start (``test_a_tilt_run_needs_a_taught_sweep_and_says_so``):
    it is never left servoing on tilts it cannot see."""
    from semservo.wire import Frame, frame_header
    from services.estimator.core import EstimatorCore, NoTiltReference, TiltSettings

    preset = PRESETS["optimal"]
    world = World(preset, speedup=1000.0)
    settings = ScanSettings(dwell_ns=preset.dwell_ns, magnification=preset.magnification,
                            working_distance_um=preset.focus_um)
    depth_of_field = 2 * settings.pixel_um / world.sem.beam_half_angle
    assert depth_of_field > 40.0
    core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE",
                         tilt=TiltSettings(depth_of_field_um=depth_of_field_um or depth_of_field,
                                           centre_um=preset.focus_um))
    pixel_nm = settings.pixel_um * 1000
    first = frame(world.sem, Pose(), settings)
    core.process(Frame(frame_header(first, seq=0, acquired_at_ns=0, pixel_size_nm=pixel_nm,
                                    magnification=preset.magnification, dwell_ns=preset.dwell_ns, source="test"), first))
    core.teach_latest()
    distances = core.next_sweep()
    pose = Pose(tilt_x_deg=3.0, tilt_y_deg=-2.0)

    def sweep(draw: int) -> np.ndarray:
        return np.stack([frame(world.sem, pose, replace(settings, working_distance_um=w), seed=draw * 100 + i)
                         for i, w in enumerate(distances)])

    estimate = estimate_tilt(sweep(0), distances, settings.pixel_um)
    assert estimate.confidence == 0.0 and np.isnan(estimate.alpha_deg) and np.isnan(estimate.beta_deg)
    assert "pin the tilts" in estimate.reason and max(estimate.alpha_uncertainty_deg, estimate.beta_uncertainty_deg) > 0.1
    # The teach may sweep the view again while pooling could pin it (the depths' scatter
    # here is not noise, so it cannot), but never more than its sweeps, and it is refused.
    with pytest.raises(NoTiltReference, match="cannot tell the tilts: .*pin the tilts"):
        for draw in range(core.tilt_settings.teach_sweeps):
            assert core.teach_tilt(sweep(draw), distances, pixel_nm) is None
    assert core.tilt_reference is None
