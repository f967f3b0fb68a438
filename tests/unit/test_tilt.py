"""Tilts from focus (semservo.estimation.tilt): the focus measure (eq. 13), the depth per kernel,
the plane fit and its sign convention, against focus sweeps of known tilted planes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from semservo.estimation.tilt import estimate_tilt, focus_curves, focus_peaks, normalized_variance

SIZE, KERNEL, PIXEL_UM = 256, 32, 0.05
WORKING_DISTANCES_UM = np.linspace(-1.5, 1.5, 13)
#: Blur (px, standard deviation) per micrometre out of focus: a small depth of field.
BLUR_PX_PER_UM = 3.0


def texture(seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return 100 + 60 * cv2.GaussianBlur(rng.normal(size=(SIZE, SIZE)), (0, 0), 1.2)


def plane_depths(alpha_deg: float, beta_deg: float, centre_um: float = 0.1, size: int = SIZE,
                 pixel_um: float = PIXEL_UM) -> np.ndarray:
    """The depth of a tilted plane at each kernel's centre (kernel rows x kernel cols):
    centre + tan(alpha) y - tan(beta) x / cos(alpha), the module's convention."""
    centres = ((np.arange(size // KERNEL) + 0.5) * KERNEL - size / 2) * pixel_um
    y, x = np.meshgrid(centres, centres, indexing="ij")
    return (centre_um + np.tan(np.radians(alpha_deg)) * y
            - np.tan(np.radians(beta_deg)) / np.cos(np.radians(alpha_deg)) * x)


def sweep_of_depths(depths: np.ndarray, scene: np.ndarray | None = None, seed: int = 5,
                    working_distances=WORKING_DISTANCES_UM) -> np.ndarray:
    """Frames of a surface whose kernels lie at ``depths`` (kernel rows x kernel cols, um)
    at each working distance: each kernel blurred by its distance from focus, with
    shot-like noise."""
    scene = texture() if scene is None else scene
    rng = np.random.default_rng(seed)
    frames = []
    for distance in working_distances:
        frame = np.empty(scene.shape)
        blurred: dict[float, np.ndarray] = {}
        for (row, col), depth in np.ndenumerate(depths):
            sigma = round(BLUR_PX_PER_UM * abs(depth - distance), 2)
            if sigma not in blurred:
                blurred[sigma] = cv2.GaussianBlur(scene, (0, 0), sigma) if sigma > 0.05 else scene
            frame[row * KERNEL:(row + 1) * KERNEL, col * KERNEL:(col + 1) * KERNEL] = \
                blurred[sigma][row * KERNEL:(row + 1) * KERNEL, col * KERNEL:(col + 1) * KERNEL]
        frames.append(frame + rng.normal(0, 1.0, frame.shape))
    return np.stack(frames)


def sweep_of_plane(alpha_deg: float, beta_deg: float, centre_um: float = 0.1, scene: np.ndarray | None = None,
                   seed: int = 5) -> np.ndarray:
    """Frames of a tilted plane at each working distance (:func:`sweep_of_depths`)."""
    return sweep_of_depths(plane_depths(alpha_deg, beta_deg, centre_um), scene, seed)


def test_the_focus_measure_is_the_variance_over_the_mean():
    assert normalized_variance(np.full((8, 8), 50.0)) == 0.0
    patch = np.array([[10.0, 30.0], [10.0, 30.0]])  # mean 20, variance 100
    assert normalized_variance(patch) == pytest.approx(5.0)
    sharp = texture()[:KERNEL, :KERNEL]
    assert normalized_variance(sharp) > normalized_variance(cv2.GaussianBlur(sharp, (0, 0), 2.0))


def test_each_kernel_focuses_at_its_own_depth_to_a_fraction_of_a_step():
    sweep = sweep_of_plane(0.0, 0.0, centre_um=0.37)  # between two working distances
    depths = focus_peaks(focus_curves(sweep, KERNEL), WORKING_DISTANCES_UM)
    assert np.isfinite(depths).all()
    assert np.median(depths) == pytest.approx(0.37, abs=0.05)


@pytest.mark.parametrize("alpha, beta", [(5.0, -3.0), (-4.0, 2.0), (0.0, 6.0), (2.0, 0.0)])
def test_known_tilts_are_recovered_with_their_signs(alpha, beta):
    estimate = estimate_tilt(sweep_of_plane(alpha, beta), WORKING_DISTANCES_UM, PIXEL_UM, kernel=KERNEL)
    assert estimate.alpha_deg == pytest.approx(alpha, abs=0.3)
    assert estimate.beta_deg == pytest.approx(beta, abs=0.3)
    assert estimate.centre_depth == pytest.approx(0.1, abs=0.1)
    assert estimate.confidence > 0.5 and estimate.kernels_used >= 40


def test_the_sign_convention_matches_the_scene():
    # alpha > 0: the lower part of the image is farther (larger working distance) and so
    # comes into focus later in the sweep; beta > 0: the right part is nearer.
    curves = focus_curves(sweep_of_plane(6.0, 0.0), KERNEL)
    depths = focus_peaks(curves, WORKING_DISTANCES_UM)
    assert np.nanmean(depths[-1]) > np.nanmean(depths[0])
    assert estimate_tilt(sweep_of_plane(6.0, 0.0), WORKING_DISTANCES_UM, PIXEL_UM, kernel=KERNEL).alpha_deg > 0
    depths = focus_peaks(focus_curves(sweep_of_plane(0.0, 6.0), KERNEL), WORKING_DISTANCES_UM)
    assert np.nanmean(depths[:, -1]) < np.nanmean(depths[:, 0])


def test_a_few_wrong_kernels_do_not_tilt_the_plane():
    sweep = sweep_of_plane(3.0, -2.0)
    # Two kernels show a bright speck in focus at the sweep's first frames only.
    for row, col in ((1, 2), (5, 6)):
        sweep[2, row * KERNEL + 10:row * KERNEL + 20, col * KERNEL + 10:col * KERNEL + 20] += 400
    estimate = estimate_tilt(sweep, WORKING_DISTANCES_UM, PIXEL_UM, kernel=KERNEL)
    assert estimate.alpha_deg == pytest.approx(3.0, abs=0.3) and estimate.beta_deg == pytest.approx(-2.0, abs=0.3)
    assert estimate.kernels_used < estimate.kernels_total


def test_a_flat_featureless_scene_is_refused_not_guessed():
    flat = np.full((SIZE, SIZE), 120.0)
    estimate = estimate_tilt(sweep_of_plane(4.0, 1.0, scene=flat), WORKING_DISTANCES_UM, PIXEL_UM, kernel=KERNEL)
    assert estimate.confidence == 0.0 and np.isnan(estimate.alpha_deg) and np.isnan(estimate.beta_deg)
    assert "clear focus peak" in estimate.reason


def test_a_sweep_that_misses_focus_is_refused():
    estimate = estimate_tilt(sweep_of_plane(2.0, 2.0, centre_um=5.0), WORKING_DISTANCES_UM, PIXEL_UM, kernel=KERNEL)
    assert estimate.confidence == 0.0 and "focus outside the sweep" in estimate.reason


@pytest.mark.parametrize("frames, distances, message", [
    (2, np.array([0.0, 1.0]), "at least 3 frames"),
    (5, np.linspace(0, 1, 4), "5 frames but 4"),
    (4, np.array([0.0, 1.0, 1.5, 3.0]), "evenly spaced"),
    (3, np.array([0.0, np.nan, 1.0]), "finite"),
])
def test_bad_sweeps_are_refused_with_the_reason(frames, distances, message):
    with pytest.raises(ValueError, match=message):
        estimate_tilt(np.full((frames, 128, 128), 100.0), distances, PIXEL_UM)


def test_non_finite_pixels_and_bad_pixel_sizes_are_refused():
    sweep = sweep_of_plane(1.0, 1.0)
    with pytest.raises(ValueError, match="pixel_size"):
        estimate_tilt(sweep, WORKING_DISTANCES_UM, float("nan"))
    sweep[3, 5, 5] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        estimate_tilt(sweep, WORKING_DISTANCES_UM, PIXEL_UM)


def test_the_papers_egi_method_recovers_a_known_tilt_between_two_sweeps():
    from semservo.estimation.tilt import depth_map, egi_tilt_between, kernel_normals

    flat = depth_map(sweep_of_plane(0.0, 0.0), WORKING_DISTANCES_UM, KERNEL)
    tilted = depth_map(sweep_of_plane(4.0, -3.0), WORKING_DISTANCES_UM, KERNEL)
    normals, weights = kernel_normals(tilted, KERNEL, PIXEL_UM)
    # Each normal points towards the lens, tipped as the plane: (-sin b, sin a cos b, -cos a cos b).
    mean = normals.mean(axis=0) / np.linalg.norm(normals.mean(axis=0))
    expected = np.array([-np.sin(np.radians(-3.0)), np.sin(np.radians(4.0)) * np.cos(np.radians(-3.0)),
                         -np.cos(np.radians(4.0)) * np.cos(np.radians(-3.0))])
    assert np.degrees(np.arccos(np.clip(mean @ expected, -1, 1))) < 0.5 and (weights >= 1).all()
    alpha, beta, peak = egi_tilt_between(flat, tilted, KERNEL, PIXEL_UM)
    assert alpha == pytest.approx(4.0, abs=0.5) and beta == pytest.approx(-3.0, abs=0.5) and peak > 1
    empty = np.full_like(flat, np.nan)
    assert np.isnan(egi_tilt_between(flat, empty, KERNEL, PIXEL_UM)[0]), "no normals: no angle"


def test_sweeps_are_planned_wide_first_then_on_the_taught_grid():
    from semservo.estimation.tilt import plan_sweep

    first = plan_sweep(0.0, 3.5, 36.0)
    assert len(first) % 2 == 1 and first[len(first) // 2] == pytest.approx(0.0)
    assert np.ptp(first) >= 2 * 36.0 * np.tan(np.radians(15.0))  # any tilt up to 15 degrees
    grid = (first[0], first[1] - first[0])
    flat, steep = (plan_sweep(0.6, 3.5, 36.0, tilt_deg=tilt, grid=grid) for tilt in ((0.0, 0.0), (10.0, 10.0)))
    assert len(flat) < len(steep) <= len(first)
    for sweep in (flat, steep):  # on the taught sweep's working distances
        assert np.allclose((sweep - grid[0]) / grid[1], np.round((sweep - grid[0]) / grid[1]))
    with pytest.raises(ValueError):
        plan_sweep(0.0, float("nan"), 36.0)


def test_a_fine_teach_sweep_lies_on_the_wide_grid_about_the_depths_found():
    from semservo.estimation.tilt import FINE_STEP_DOF, MARGIN_DOF, plan_fine_sweep, plan_sweep

    depth_of_field = 2.5
    wide = plan_sweep(0.0, depth_of_field, 25.0)  # 1.25 um apart
    depths = np.full((8, 8), np.nan)
    depths[2:6, 3:7] = np.linspace(-0.3, 0.4, 16).reshape(4, 4)  # a bunched, slightly tilted cluster
    depths[0, 0] = wide[0] + 0.1  # a marginal peak read at the sweep's end
    fine = plan_fine_sweep(depths, wide, depth_of_field)
    step = fine[1] - fine[0]
    assert step == pytest.approx(FINE_STEP_DOF * depth_of_field) and np.ptp(np.diff(fine)) < 1e-9
    on_grid = (fine - wide[0]) / step
    assert np.allclose(on_grid, np.round(on_grid))  # every wide sample is on it too
    margin = MARGIN_DOF * depth_of_field
    assert fine[0] <= -0.3 - margin + 1e-9 and fine[-1] >= 0.4 + margin - 1e-9
    assert fine[0] > -0.3 - margin - step and fine[-1] < 0.4 + margin + step  # not out to the odd kernel
    # On a fine grid already taught, from a wide sweep off it (a run's): on that grid.
    taught_grid = (fine[0] + 0.3 * step, step)
    kept = plan_fine_sweep(depths, wide + 0.4, depth_of_field, grid=taught_grid)
    on_taught = (kept - taught_grid[0]) / step
    assert np.allclose(on_taught, np.round(on_taught)) and np.allclose(np.diff(kept), step)
    # Kernels over too many depths for 25 frames at that step: none (the wide sweeps stand).
    assert plan_fine_sweep(np.linspace(-6, 6, 64).reshape(8, 8), wide, depth_of_field) is None
    assert plan_fine_sweep(np.full((8, 8), np.nan), wide, depth_of_field) is None


def test_a_sweep_is_as_fine_as_a_grid_when_its_samples_are_no_farther_apart():
    from semservo.estimation.tilt import sampled_as_finely

    grid_step = 0.625
    assert sampled_as_finely(np.arange(17) * grid_step + 3.0, grid_step)
    assert sampled_as_finely(np.arange(17) * grid_step * 1.005, grid_step)  # rounding, not coarser
    assert sampled_as_finely(np.arange(40) * 0.3, grid_step)  # finer
    assert not sampled_as_finely(np.arange(21) * 1.25, grid_step)  # a wide sweep
    assert not sampled_as_finely([2.0], grid_step)  # one frame has no step


def test_fine_sweeps_are_for_a_teach_pinned_too_loosely_not_for_one_refused_otherwise():
    from dataclasses import replace

    from semservo.estimation.tilt import MAX_TAUGHT_UNCERTAINTY_DEG, MIN_KERNELS, TiltEstimate, wants_fine_sweeps

    loose = TiltEstimate(0.1, 0.2, 0.0, 40, 256, 0.05, 0.9, "", 0.08, 0.06)  # taught alone, over a teach's line
    assert wants_fine_sweeps(loose) and not wants_fine_sweeps(replace(loose, alpha_uncertainty_deg=0.05))
    refused = replace(loose, alpha_deg=np.nan, beta_deg=np.nan, confidence=0.0, alpha_uncertainty_deg=0.2,
                      reason="the 40 kernels that see focus ... pin the tilts to +-0.20")
    assert wants_fine_sweeps(refused)
    # Refused for its scatter (under the 0.1 line) or too few kernels: finer sampling does not help.
    assert not wants_fine_sweeps(replace(refused, alpha_uncertainty_deg=0.09))
    assert not wants_fine_sweeps(replace(refused, kernels_used=MIN_KERNELS - 1))
    assert not wants_fine_sweeps(replace(refused, alpha_uncertainty_deg=np.nan, beta_uncertainty_deg=np.nan))
    assert not wants_fine_sweeps(loose, line_deg=0.1) and MAX_TAUGHT_UNCERTAINTY_DEG < 0.08


def test_undoing_the_foreshortening_restores_the_square_view():
    from semservo.estimation.tilt import undo_foreshortening

    scene = texture().astype(np.float32)
    # Foreshorten rows by cos(20 degrees) (a tilt about x), then undo it.
    size = scene.shape[0]
    centred = np.arange(size, dtype=np.float32) - (size - 1) / 2
    rows = (centred[:, None] / np.cos(np.radians(20.0)) + (size - 1) / 2).astype(np.float32)
    cols = np.broadcast_to(np.arange(size, dtype=np.float32)[None, :], scene.shape)
    tilted = cv2.remap(scene, np.ascontiguousarray(cols), np.ascontiguousarray(np.broadcast_to(rows, scene.shape)),
                       cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    restored = undo_foreshortening(tilted, 20.0, 0.0)
    middle = (slice(64, -64), slice(64, -64))
    assert np.corrcoef(restored[middle].ravel(), scene[middle].ravel())[0, 1] > 0.98
    assert np.corrcoef(tilted[middle].ravel(), scene[middle].ravel())[0, 1] < 0.8


def test_the_old_module_name_is_the_same_module():
    """Lab scripts written against ``semservo.tilt`` keep working: the name is the tilt
    section of the estimation package itself, not a copy."""
    import semservo.estimation.tilt
    import semservo.tilt
    from semservo.tilt import estimate_tilt as old_name

    assert semservo.tilt is semservo.estimation.tilt
    assert old_name is semservo.estimation.tilt.estimate_tilt


def test_noise_is_taken_out_of_the_focus_measure():
    """Eq. 13's variance over the mean, split (lags 1 and 2 against lag 0): white noise
    lands in the noise share, and the scene's share is the same with and without it."""
    from semservo.estimation.tilt import noise_free_focus_curves

    sweep = sweep_of_plane(0.0, 0.0)[:, :128, :128]
    rng = np.random.default_rng(4)
    noisy = sweep + rng.normal(0, 6.0, sweep.shape)
    clean_curves, noisy_curves = noise_free_focus_curves(sweep, KERNEL), noise_free_focus_curves(noisy, KERNEL)
    mean_level = sweep.mean()
    assert np.median(noisy_curves.noise - clean_curves.noise) == pytest.approx(36.0 / mean_level, rel=0.15)
    in_focus = np.argmax(clean_curves.signal.mean(axis=(1, 2)))
    assert np.allclose(noisy_curves.signal[in_focus], clean_curves.signal[in_focus], rtol=0.2)
    assert noisy_curves.pixels == KERNEL * KERNEL


def test_kernels_of_noise_only_show_no_focus_peak():
    """A flat scene under heavy noise: eq. 13's variance over the mean of noise wanders
    from frame to frame and made "peaks" microns off; without the noise it has none."""
    from semservo.estimation.tilt import clear_focus_peaks, noise_free_focus_curves

    rng = np.random.default_rng(8)
    flat = np.full((len(WORKING_DISTANCES_UM), SIZE, SIZE), 40.0) + rng.normal(0, 8.0, (len(WORKING_DISTANCES_UM),
                                                                                      SIZE, SIZE))
    depths = clear_focus_peaks(noise_free_focus_curves(flat, KERNEL), WORKING_DISTANCES_UM)
    assert np.isfinite(depths).sum() <= 1
    textured = sweep_of_plane(2.0, -1.0) + rng.normal(0, 8.0, (len(WORKING_DISTANCES_UM), SIZE, SIZE))
    assert np.isfinite(clear_focus_peaks(noise_free_focus_curves(textured, KERNEL), WORKING_DISTANCES_UM)).all()


def test_the_robust_plane_gives_wrong_kernels_no_weight():
    from semservo.estimation.tilt import robust_plane

    rows, cols = np.mgrid[0:8, 0:8]
    depths = 0.2 + 0.01 * (cols - 3.5) * KERNEL * PIXEL_UM - 0.02 * (rows - 3.5) * KERNEL * PIXEL_UM
    depths = depths + np.random.default_rng(2).normal(0, 0.01, depths.shape)
    depths[1, 2], depths[6, 6], depths[3, 0] = 3.0, -2.5, 1.1  # peaks of noise, microns off
    plane = robust_plane(depths, KERNEL, PIXEL_UM)
    assert plane.coefficients == pytest.approx([0.2, 0.01, -0.02], abs=0.003)
    assert plane.weights[1, 2] == plane.weights[6, 6] == plane.weights[3, 0] == 0
    assert (plane.weights > 0).sum() == 61 and plane.scale == pytest.approx(0.01, rel=0.4)
    assert np.all(np.isfinite(plane.covariance)) and plane.covariance[1, 1] > 0


def test_kernels_bunched_in_a_corner_cannot_pin_the_tilts_and_say_so():
    """Texture in one corner only (a few particles on a dark ground): the kernels that
    see focus span too little of the field, and the tilts are refused with the reason,
    not guessed from a plane that tips on them."""
    scene = np.full((SIZE, SIZE), 100.0)
    scene[:96, :96] = texture()[:96, :96]  # 3 x 3 kernels of 8 x 8
    rng = np.random.default_rng(3)
    sweep = sweep_of_plane(3.0, 2.0, scene=scene) + rng.normal(0, 1.0, (len(WORKING_DISTANCES_UM), SIZE, SIZE))
    estimate = estimate_tilt(sweep, WORKING_DISTANCES_UM, PIXEL_UM, kernel=KERNEL)
    assert estimate.confidence == 0.0 and np.isnan(estimate.alpha_deg)
    assert "kernels" in estimate.reason and "pin the tilts" in estimate.reason and "of the field" in estimate.reason
    assert estimate.alpha_uncertainty_deg > 0.1


def test_a_scene_of_two_planes_is_refused_not_averaged():
    """Half the field in focus 1 um deeper than the other half (a step, or a sample that
    is not flat): no single plane holds, and the estimate says so."""
    top = sweep_of_plane(0.0, 0.0, centre_um=-0.6)
    bottom = sweep_of_plane(0.0, 0.0, centre_um=0.6)
    sweep = np.concatenate([top[:, :SIZE // 2], bottom[:, SIZE // 2:]], axis=1)
    steps = np.diff(WORKING_DISTANCES_UM).mean()
    estimate = estimate_tilt(sweep, WORKING_DISTANCES_UM, PIXEL_UM, kernel=KERNEL)
    assert estimate.confidence == 0.0 and np.isnan(estimate.alpha_deg), estimate
    assert "scatter" in estimate.reason or "pin the tilts" in estimate.reason
    assert estimate.residual > 0.3 * steps


def test_a_good_estimate_carries_small_uncertainties():
    estimate = estimate_tilt(sweep_of_plane(4.0, -2.0), WORKING_DISTANCES_UM, PIXEL_UM, kernel=KERNEL)
    assert estimate.reason == "" and estimate.confidence > 0.5
    assert 0 < estimate.alpha_uncertainty_deg < 0.1 and 0 < estimate.beta_uncertainty_deg < 0.1


# --------------------------------------------------------------------------------------
# Every refusal of tilt_from_depths, each for its own reason, on synthetic sweeps


def sweep_of_particles(kernel_depths: dict[tuple[int, int], float], seed: int = 5) -> np.ndarray:
    """Texture in a few kernels only (particles on a featureless ground), each kernel's
    texture at its own depth; every other kernel out of focus over the whole sweep, its
    texture kept inside the kernel so that none bleeds into a neighbour."""
    depths = np.full((SIZE // KERNEL, SIZE // KERNEL), 5.0)
    scene, sharp = np.full((SIZE, SIZE), 100.0), texture()
    for (row, col), depth in kernel_depths.items():
        depths[row, col] = depth
        inside = (slice(row * KERNEL + 6, (row + 1) * KERNEL - 6), slice(col * KERNEL + 6, (col + 1) * KERNEL - 6))
        scene[inside] = sharp[inside]
    return sweep_of_depths(depths, scene, seed)


def test_too_few_kernels_in_focus_are_refused_with_the_count():
    """Five particles in focus: fewer than MIN_KERNELS kernels with a clear peak."""
    from semservo.estimation.tilt import MIN_KERNELS

    particles = {(1, 1): 0.1, (1, 6): 0.2, (6, 1): -0.1, (6, 6): 0.0, (3, 4): 0.1}
    estimate = estimate_tilt(sweep_of_particles(particles), WORKING_DISTANCES_UM, PIXEL_UM, kernel=KERNEL)
    assert estimate.confidence == 0.0 and np.isnan(estimate.alpha_deg) and np.isnan(estimate.beta_deg)
    assert estimate.kernels_used == len(particles) < MIN_KERNELS
    assert estimate.reason.startswith(f"only {len(particles)} of 64 kernels have a clear focus peak")


def test_a_plane_that_holds_for_too_few_kernels_is_refused():
    """Six particles see focus, but one lies 0.8 um off the plane of the other five: the
    robust plane leaves it out, and fewer than MIN_KERNELS remain to trust."""
    particles = {(1, 1): 0.1, (1, 6): 0.1, (6, 1): 0.1, (6, 6): 0.1, (3, 4): 0.1, (4, 2): 0.9}
    estimate = estimate_tilt(sweep_of_particles(particles), WORKING_DISTANCES_UM, PIXEL_UM, kernel=KERNEL)
    assert estimate.confidence == 0.0 and np.isnan(estimate.alpha_deg)
    assert "the plane holds for only" in estimate.reason and "of the 6 kernels with a clear focus peak" in estimate.reason
    assert estimate.kernels_used < 6


def test_a_rough_surface_is_refused_for_its_scatter_or_its_uncertainty():
    """Every kernel in focus at its own depth, +-0.3 um about a tilted plane (a rough
    sample: 1.2 sweep steps of spread). Over a 64 um field the plane's slopes are pinned
    well enough (standard errors under 0.1 degree), so the scatter is the reason; over a
    13 um field (the same sweep, smaller pixels) the slopes are not, and that is."""
    from semservo.estimation.tilt import MAX_SCATTER_STEPS, MAX_TILT_UNCERTAINTY_DEG

    rng = np.random.default_rng(0)
    depths = plane_depths(2.0, -1.0, 0.1, pixel_um=0.25) + rng.uniform(-0.3, 0.3, (SIZE // KERNEL,) * 2)
    sweep = sweep_of_depths(depths)
    step = float(np.diff(WORKING_DISTANCES_UM).mean())
    wide = estimate_tilt(sweep, WORKING_DISTANCES_UM, 0.25, kernel=KERNEL)
    assert wide.confidence == 0.0 and np.isnan(wide.alpha_deg)
    assert max(wide.alpha_uncertainty_deg, wide.beta_uncertainty_deg) <= MAX_TILT_UNCERTAINTY_DEG
    assert wide.reason.startswith("the kernel depths scatter about the plane by") and "not one plane" in wide.reason
    # Every kernel sees focus; the robust plane may leave out one at the roughness's extremes.
    assert wide.residual > MAX_SCATTER_STEPS * step and wide.kernels_used >= 60
    narrow = estimate_tilt(sweep, WORKING_DISTANCES_UM, PIXEL_UM, kernel=KERNEL)
    assert narrow.confidence == 0.0 and "pin the tilts" in narrow.reason and "100% x 100% of the field" in narrow.reason
    assert min(narrow.alpha_uncertainty_deg, narrow.beta_uncertainty_deg) > MAX_TILT_UNCERTAINTY_DEG


def test_the_same_plane_without_the_roughness_is_measured():
    """The control for the test above: the plane alone, over the same 64 um field."""
    sweep = sweep_of_depths(plane_depths(2.0, -1.0, 0.1, pixel_um=0.25))
    estimate = estimate_tilt(sweep, WORKING_DISTANCES_UM, 0.25, kernel=KERNEL)
    assert estimate.reason == "" and estimate.confidence > 0.5
    assert estimate.alpha_deg == pytest.approx(2.0, abs=0.1) and estimate.beta_deg == pytest.approx(-1.0, abs=0.1)


# -- the taught pose swept more than once, the depths pooled ------------------------------

def noisy_depth_maps(count: int, noise_um: float, seed: int = 11, alpha_deg: float = 2.0,
                     beta_deg: float = -1.0) -> list[np.ndarray]:
    """``count`` depth maps of the same plane, each kernel's depth off by independent
    Gaussian noise (``noise_um``): what sweeps of one view give where pixel noise decides."""
    rng = np.random.default_rng(seed)
    truth = plane_depths(alpha_deg, beta_deg)
    return [truth + rng.normal(0.0, noise_um, truth.shape) for _ in range(count)]


def test_pooled_depths_weigh_each_sweep_by_its_uncertainty():
    """Inverse-variance weighting: a depth twice as uncertain weighs a quarter as much,
    and the pooled uncertainty is 1 / sqrt(sum of the weights)."""
    from semservo.estimation.tilt import KernelDepths, pool_depths

    precise = KernelDepths(np.array([[1.0, 4.0]]), np.array([[0.1, 0.2]]))
    loose = KernelDepths(np.array([[2.0, np.nan]]), np.array([[0.2, np.nan]]))
    pooled = pool_depths([precise, loose])
    assert pooled.depths[0, 0] == pytest.approx((1.0 / 0.01 + 2.0 / 0.04) / (1 / 0.01 + 1 / 0.04))
    assert pooled.uncertainties[0, 0] == pytest.approx(1 / np.sqrt(1 / 0.01 + 1 / 0.04))
    assert pooled.depths[0, 1] == 4.0 and pooled.uncertainties[0, 1] == pytest.approx(0.2)


def test_pooled_depths_are_each_kernels_mean_where_half_the_sweeps_see_it():
    from semservo.estimation.tilt import pool_depths

    first = np.array([[1.0, np.nan], [3.0, np.nan]])
    second = np.array([[3.0, 2.0], [np.nan, np.nan]])
    third = np.array([[2.0, np.nan], [np.nan, 5.0]])
    pooled = pool_depths([first, second]).depths
    assert pooled[0, 0] == 2.0 and pooled[0, 1] == 2.0 and pooled[1, 0] == 3.0 and np.isnan(pooled[1, 1])
    # Of three sweeps, a kernel seen in one only is left out (a marginal peak).
    pooled = pool_depths([first, second, third]).depths
    assert pooled[0, 0] == 2.0 and np.isnan(pooled[0, 1]) and np.isnan(pooled[1, 0]) and np.isnan(pooled[1, 1])
    np.testing.assert_array_equal(pool_depths([first]).depths, first)
    with pytest.raises(ValueError, match="same shape"):
        pool_depths([first, np.zeros((3, 3))])
    with pytest.raises(ValueError, match="one or more"):
        pool_depths([])


def test_pooling_sweeps_narrows_the_tilts_about_as_one_over_the_root_of_their_number():
    from semservo.estimation.tilt import MAX_TILT_UNCERTAINTY_DEG, pooled_tilt, tilt_from_depths

    step = float(WORKING_DISTANCES_UM[1] - WORKING_DISTANCES_UM[0])
    singles, pooled = [], []
    for seed in range(8):
        maps = noisy_depth_maps(4, noise_um=0.07, seed=seed)
        singles.append(tilt_from_depths(maps[0], KERNEL, PIXEL_UM, step))
        pooled.append(pooled_tilt(maps, KERNEL, PIXEL_UM, step))
    single_uncertainty = np.mean([each.alpha_uncertainty_deg for each in singles])
    pooled_uncertainty = np.mean([each.alpha_uncertainty_deg for each in pooled])
    # One sweep alone cannot pin these tilts: refused, with how well it pinned them.
    assert single_uncertainty > MAX_TILT_UNCERTAINTY_DEG
    assert all(each.confidence == 0 and "pin the tilts" in each.reason for each in singles)
    # Four pooled: about half the uncertainty (1 / sqrt(4), the floor of the sampling bias aside).
    assert 0.4 < pooled_uncertainty / single_uncertainty < 0.65
    assert all(each.sweeps == 4 and each.confidence > 0 for each in pooled)
    # ... and the estimates' scatter about the truth shrinks with it.
    errors = np.array([[each.alpha_deg - 2.0, each.beta_deg + 1.0] for each in pooled])
    assert np.abs(errors).max() < 3 * pooled_uncertainty


def test_a_teach_sweeps_again_while_the_tilts_are_pinned_loosely_and_stops_at_the_bound():
    from semservo.estimation.tilt import (MAX_TEACH_SWEEPS, TEACH_UNCERTAINTY_DEG, pooled_tilt,
                                          wants_another_sweep)

    step = float(WORKING_DISTANCES_UM[1] - WORKING_DISTANCES_UM[0])

    def teach(maps: list[np.ndarray], max_sweeps: int = MAX_TEACH_SWEEPS):
        """The teach's loop: sweep, pool, again while asked (as the estimator service's)."""
        taken = []
        for depths in maps:
            taken.append(depths)
            estimate = pooled_tilt(taken, KERNEL, PIXEL_UM, step)
            if not wants_another_sweep(estimate, max_sweeps):
                return estimate
        raise AssertionError("asked for more sweeps than the bound")

    # Pinned well by one sweep: one sweep.
    assert teach(noisy_depth_maps(8, noise_um=0.005)).sweeps == 1
    # Pinned loosely (refused alone): sweeps again, accepted once pooled, within the bound.
    loose = teach(noisy_depth_maps(8, noise_um=0.08))
    assert 1 < loose.sweeps <= MAX_TEACH_SWEEPS and loose.confidence > 0
    # Accepted alone but over the teach's aim: pooled to under it.
    aimed = teach(noisy_depth_maps(8, noise_um=0.03))
    assert aimed.sweeps > 1 and max(aimed.alpha_uncertainty_deg, aimed.beta_uncertainty_deg) <= TEACH_UNCERTAINTY_DEG
    # The bound holds whatever the sweeps say: never more than max_sweeps.
    assert teach(noisy_depth_maps(8, noise_um=0.05), max_sweeps=2).sweeps == 2


def test_a_hopeless_texture_is_refused_at_once_with_how_well_it_pinned_the_tilts():
    from semservo.estimation.tilt import MAX_TILT_UNCERTAINTY_DEG, pooled_tilt, wants_another_sweep

    step = float(WORKING_DISTANCES_UM[1] - WORKING_DISTANCES_UM[0])
    # So noisy that even four sweeps at 1 / sqrt(n) could not pin the tilts: not swept again.
    estimate = pooled_tilt(noisy_depth_maps(1, noise_um=0.3), KERNEL, PIXEL_UM, step)
    assert estimate.confidence == 0 and np.isnan(estimate.alpha_deg)
    assert estimate.alpha_uncertainty_deg > 2 * MAX_TILT_UNCERTAINTY_DEG
    assert "pin the tilts to +-" in estimate.reason
    assert not wants_another_sweep(estimate)
    # Refused after the bound, the reason says after how many sweeps and how well.
    pooled = pooled_tilt(noisy_depth_maps(4, noise_um=0.3), KERNEL, PIXEL_UM, step)
    assert pooled.confidence == 0 and pooled.sweeps == 4 and not wants_another_sweep(pooled)
    assert pooled.reason.startswith("after 4 sweeps pooled, ") and "pin the tilts to +-" in pooled.reason
    # Refused for another reason than its uncertainty (too few kernels): not swept again.
    few = np.full((SIZE // KERNEL, SIZE // KERNEL), np.nan)
    few[0, :3] = 0.1
    refused = pooled_tilt([few], KERNEL, PIXEL_UM, step)
    assert refused.confidence == 0 and "clear focus peak" in refused.reason and not wants_another_sweep(refused)
    # Once pooled, a view refused after 3 sweeps is swept a fourth time where 1 / sqrt(n)
    # projects a little over the line from there (POOLING_SLACK): the pooled standard
    # error is an estimate too.
    from dataclasses import replace

    marginal = replace(estimate, sweeps=3, alpha_uncertainty_deg=1.2 * MAX_TILT_UNCERTAINTY_DEG,
                       beta_uncertainty_deg=1.1 * MAX_TILT_UNCERTAINTY_DEG)
    assert wants_another_sweep(marginal) and not wants_another_sweep(replace(marginal, sweeps=4))
    # Far over the line even then (2 sweeps at twice the line project 1.4 x it for 4): refused.
    assert not wants_another_sweep(replace(marginal, sweeps=2, alpha_uncertainty_deg=2 * MAX_TILT_UNCERTAINTY_DEG))
    # The first of a teach's fine sweeps, after its wide ones: pooling has begun, the slack holds.
    first_fine = replace(marginal, sweeps=1, alpha_uncertainty_deg=2.4 * MAX_TILT_UNCERTAINTY_DEG)  # 1.2 x for 4
    assert not wants_another_sweep(first_fine) and wants_another_sweep(first_fine, begun=True)
    # A plane that holds for too few kernels is refused for that, however its errors read.
    from semservo.estimation.tilt import MIN_KERNELS

    assert not wants_another_sweep(replace(marginal, kernels_used=MIN_KERNELS - 1))


def test_the_benchmarks_teach_pools_its_reference_as_the_service_does():
    from semservo.reproduce.tilts import teach_reference

    faint = 100 + 3.5 * (texture() - 100) / 60

    class FaintLab:
        """A flat view of a faint texture: one sweep pins its tilts to about a tenth of a degree."""

        pixel_um = PIXEL_UM

        def __init__(self):
            self.sweeps = 0

        def sweep(self, pose, working_distances):
            self.sweeps += 1
            return sweep_of_depths(plane_depths(*pose[:2]), faint, seed=self.sweeps)

    lab = FaintLab()
    pooled, depths, _ = teach_reference(lab, WORKING_DISTANCES_UM, max_sweeps=4)
    assert 1 < pooled.sweeps == lab.sweeps <= 4 and pooled.confidence > 0 and depths.shape == (SIZE // KERNEL,) * 2
    assert pooled.alpha_deg == pytest.approx(0.0, abs=0.3) and pooled.beta_deg == pytest.approx(0.0, abs=0.3)
    single = teach_reference(FaintLab(), WORKING_DISTANCES_UM, max_sweeps=1).estimate
    assert single.sweeps == 1


def test_the_benchmarks_teach_sweeps_finely_where_the_wide_sweeps_cannot_as_the_service_does():
    from semservo.reproduce.tilts import teach_reference

    faint = 100 + 3.5 * (texture() - 100) / 60

    class FaintLab:
        """A flat view of a faint texture, swept where it is asked (a depth of field of 0.5 um)."""

        pixel_um, depth_of_field_um = PIXEL_UM, 0.5

        def __init__(self):
            self.plans = []

        def sweep(self, pose, working_distances):
            self.plans.append(np.asarray(working_distances))
            return sweep_of_depths(plane_depths(*pose[:2]), faint, seed=len(self.plans),
                                   working_distances=working_distances)

    lab = FaintLab()
    taught, _, swept = teach_reference(lab, WORKING_DISTANCES_UM, max_sweeps=1)
    wide_step = WORKING_DISTANCES_UM[1] - WORKING_DISTANCES_UM[0]
    assert np.array_equal(lab.plans[0], WORKING_DISTANCES_UM) and len(lab.plans) > 1
    assert all(np.array_equal(plan, swept) for plan in lab.plans[1:]) and swept[1] - swept[0] == pytest.approx(
        wide_step / 2)
    assert taught.sweeps == len(lab.plans) - 1  # the fine ones, pooled apart from the wide one
    assert taught.confidence > 0 and max(taught.alpha_uncertainty_deg, taught.beta_uncertainty_deg) <= 0.071
    assert abs(taught.alpha_deg) < 0.2 and abs(taught.beta_deg) < 0.2
    # Without fine sweeps the same teach is refused (one wide sweep pins it to +-0.08-0.1 degree).
    never = teach_reference(FaintLab(), WORKING_DISTANCES_UM, max_sweeps=1, fine_sweeps=0)
    assert np.array_equal(never.working_distances, WORKING_DISTANCES_UM) and never.estimate.sweeps == 1
    assert never.estimate.confidence == 0 and "pin the tilts" in never.estimate.reason


# --------------------------------------------------------------------------------------
# Each kernel's depth where its texture lies, moved to the kernel's centre


def test_a_kernels_texture_offset_is_where_its_focus_peak_comes_from():
    """One particle 10 px right of and 6 px above a kernel's centre, blurred by the sweep:
    the centroid of its share of the peak is there, not at the centre."""
    from semservo.estimation.tilt import noise_free_focus_curves, texture_offsets

    scene = np.full((SIZE, SIZE), 100.0)
    row, col = 2 * KERNEL + KERNEL // 2 - 6, 5 * KERNEL + KERNEL // 2 + 10  # kernel (2, 5)
    scene[row - 2:row + 2, col - 2:col + 2] = 250.0
    depths = np.full((SIZE // KERNEL, SIZE // KERNEL), 0.1)
    sweep = sweep_of_depths(depths, scene)
    offsets = texture_offsets(sweep, noise_free_focus_curves(sweep, KERNEL), KERNEL)
    # The 4 x 4 particle's centre lies half a pixel up and left of (row, col); the
    # kernel's centre at 2 * 32 + 15.5, 5 * 32 + 15.5.
    assert offsets[2, 5] == pytest.approx([-6.0, 10.0], abs=0.5)
    assert np.abs(offsets[0, 0]).max() < KERNEL / 2


def test_tilts_of_a_patch_of_particles_are_not_read_small():
    """Particles only in a disc about the field's centre (a cluster on a bare ground, as
    on the drift pair), on a plane whose every pixel lies at its own depth
    (semservo.focus_sweeps): at the disc's rim each kernel's texture lies towards the
    inside, so with the depths placed at the kernel centres the plane is squeezed and
    the tilts read about 4 % small (0.3 degree of 6-8); moved to the kernel centres, the
    tilts hold."""
    from semservo.estimation.tilt import depth_map, plan_sweep, robust_plane
    from semservo.focus_sweeps import DefocusModel, TiltedTexture

    size, pixel_um, kernel = 384, 0.05, 32
    rng = np.random.default_rng(4)
    rows, cols = np.mgrid[0:size, 0:size]
    scene = np.full((size, size), 60.0)
    for _ in range(1500):
        y, x = rng.uniform(0, size, 2)
        if np.hypot(y - size / 2, x - size / 2) < 110:
            scene += 150 * np.exp(-((rows - y) ** 2 + (cols - x) ** 2) / (2 * 1.2**2))

    def tilts(depths):
        return robust_plane(depths, kernel, pixel_um).tilts_deg

    for pose in ((6.0, 0.0, 0.0), (0.0, -8.0, 0.0)):
        working_distances = plan_sweep(0.0, 0.5, size * pixel_um)
        sweep = TiltedTexture(scene, DefocusModel("gaussian", depth_of_field_um=0.5), pixel_um, shape=(size, size),
                              pose=pose).sweep(working_distances, np.random.default_rng(1))
        at_texture = np.subtract(tilts(depth_map(sweep, working_distances, kernel)), pose[:2])
        at_centres = np.subtract(tilts(depth_map(sweep, working_distances, kernel, pixel_um)), pose[:2])
        assert np.abs(at_texture).max() > 0.25  # the old reading: squeezed
        assert np.abs(at_centres).max() < 0.15
        # The estimate (each kernel weighed by its uncertainty) holds as well.
        estimate = estimate_tilt(sweep, working_distances, pixel_um, kernel=kernel)
        assert np.abs(np.subtract((estimate.alpha_deg, estimate.beta_deg), pose[:2])).max() < 0.15


def test_a_focus_curves_scatter_is_its_noise_not_its_peak():
    """Measured on the curve itself: the frame-to-frame scatter of a peaked curve plus
    noise is about the noise's standard deviation (the median leaves out most of the
    peak's bend, not all); a sharp peak's bend alone counts for under 1 % of its height; too
    short a sweep gives none (0: the modelled error alone decides)."""
    from semservo.estimation.tilt import focus_curve_scatter

    rng = np.random.default_rng(4)
    steps = np.arange(21) - 10.0
    shape = 1.0 / (0.6 + np.abs(steps)[:, None] + np.zeros((1, 400))) ** 2  # a texture's 1 / s^2, 400 kernels
    flat = rng.normal(0.0, 0.3, shape.shape)
    assert np.median(focus_curve_scatter(flat)) == pytest.approx(0.3, rel=0.1)
    noisy = 20.0 * shape + flat  # a peak of 56, about 180 noise deviations
    assert 0.3 < np.median(focus_curve_scatter(noisy)) < 2 * 0.3
    sharp = 1000.0 * shape
    assert (focus_curve_scatter(sharp) < 0.01 * sharp.max(axis=0)).all()
    assert (focus_curve_scatter(noisy[4:-5]) == 0).all()  # 12 frames


def test_a_peak_of_noise_the_modelled_error_misses_is_not_a_focus_peak():
    """A kernel whose curve wanders by more than pixel noise alone would make it (the
    scene's part of the variance's scatter, the mean's noise): its highest value stands
    8 modelled standard errors over its lowest, but a few of its own; it has no depth.
    A texture's peak, as high over the same noise, keeps its depth."""
    from semservo.estimation.tilt import FocusCurves, clear_focus_peaks

    rng = np.random.default_rng(8)
    frames, pixels = 21, 32 * 32
    noise = np.full((frames, 1, 2), 3.2)  # the noise's share: a modelled standard error of 0.1
    wandering = rng.normal(1.0, 0.3, (frames, 1, 2))
    wandering[10, 0, 0] = 2.2  # 12 modelled standard errors over the lowest: a "peak" to the model
    wandering[:, 0, 1] += 20.0 / (0.6 + np.abs(np.arange(frames) - 10.0)) ** 2  # a texture in focus at frame 10
    depths = clear_focus_peaks(FocusCurves(wandering, noise, pixels), np.arange(frames, dtype=float))
    assert np.isnan(depths[0, 0])
    assert depths[0, 1] == pytest.approx(10.0, abs=0.3)


def test_the_jackknife_fits_every_kernel_left_out_at_once_as_one_refit_each_would():
    """The jackknife's refits, made all at once, are each the robust plane fitted again
    without one kernel: on depths with outliers, kernels missing and uneven
    uncertainties, the covariance equals the one from a refit per kernel."""
    from semservo.estimation.tilt import jackknife_slopes_covariance, robust_plane

    rng = np.random.default_rng(5)
    for case in range(6):
        depths = plane_depths(3.0 * rng.standard_normal(), 3.0 * rng.standard_normal())
        depths = depths + rng.normal(0.0, 0.05, depths.shape)
        depths[rng.random(depths.shape) < 0.3] = np.nan  # kernels without a clear peak
        wrong = rng.random(depths.shape) < 0.05
        depths[wrong] += rng.normal(0.0, 3.0, wrong.sum())  # peaks of noise, microns off
        uncertainties = None if case % 2 else np.exp(rng.normal(-3.0, 0.7, depths.shape))
        kernels = np.argwhere(np.isfinite(depths))
        slopes = []
        for row, col in kernels:
            without = depths.copy()
            without[row, col] = np.nan
            slopes.append(robust_plane(without, KERNEL, PIXEL_UM, uncertainties=uncertainties).coefficients[1:])
        deviations = np.asarray(slopes) - np.mean(slopes, axis=0)
        one_by_one = (len(kernels) - 1) / len(kernels) * deviations.T @ deviations
        at_once = jackknife_slopes_covariance(depths, KERNEL, PIXEL_UM, uncertainties)
        assert at_once == pytest.approx(one_by_one, rel=1e-8, abs=1e-15)


def test_the_tilts_standard_errors_hold_where_kernels_differ_in_noise():
    """The jackknife over kernels: where the kernels at the field's edges are four times
    noisier than those inside (a textured band fainter at its ends), the standard
    errors from the residuals' robust scale see the many precise kernels and are too
    small; the jackknife's match the estimates' scatter over noise draws."""
    from semservo.estimation.tilt import jackknife_slopes_covariance, robust_plane, tilt_from_depths

    truth = plane_depths(2.0, -1.0)
    rows, cols = np.indices(truth.shape)
    edge = (np.minimum.reduce([rows, cols, truth.shape[0] - 1 - rows, truth.shape[1] - 1 - cols]) == 0)
    noise_um = np.where(edge, 0.2, 0.05)
    rng = np.random.default_rng(21)
    step = float(WORKING_DISTANCES_UM[1] - WORKING_DISTANCES_UM[0])
    slopes, jackknifed, from_residuals = [], [], []
    for _ in range(60):
        depths = truth + rng.normal(0.0, 1.0, truth.shape) * noise_um
        plane = robust_plane(depths, KERNEL, PIXEL_UM)
        slopes.append(plane.coefficients[2])
        jackknifed.append(np.sqrt(jackknife_slopes_covariance(depths, KERNEL, PIXEL_UM)[1, 1]))
        from_residuals.append(np.sqrt(plane.covariance[2, 2]))
    scatter = np.std(slopes)
    assert np.mean(from_residuals) < 0.8 * scatter  # too small: the precise kernels set the scale
    assert 0.8 * scatter < np.mean(jackknifed) < 1.3 * scatter
    # The estimate carries the jackknife's standard errors (over the sampling bias's floor).
    estimate = tilt_from_depths(depths, KERNEL, PIXEL_UM, step)
    assert estimate.alpha_uncertainty_deg == pytest.approx(np.degrees(jackknifed[-1]), rel=0.1)
    assert (jackknife_slopes_covariance(np.full((8, 8), np.nan), KERNEL, PIXEL_UM) == np.inf).all()


# --------------------------------------------------------------------------------------
# Each kernel weighed by how well its focus curve pins its depth


def test_a_faint_kernels_depth_is_given_a_larger_uncertainty():
    """Half the field of full contrast, half of a tenth of it, the same noise: the faint
    kernels' depths scatter more over noise draws, and their uncertainties (from the
    focus curve's noise alone) say so, in rank and roughly in size."""
    from semservo.estimation.tilt import (DEPTH_UNCERTAINTY_FLOOR_STEPS, clear_focus_peaks, focus_peak_uncertainties,
                                          noise_free_focus_curves)

    scene = texture()
    scene[:, SIZE // 2:] = 100 + (scene[:, SIZE // 2:] - 100) / 10
    depths, uncertainties = [], []
    for seed in range(8):
        curves = noise_free_focus_curves(sweep_of_plane(0.0, 0.0, scene=scene, seed=seed), KERNEL)
        depths.append(clear_focus_peaks(curves, WORKING_DISTANCES_UM))
        uncertainties.append(focus_peak_uncertainties(curves, WORKING_DISTANCES_UM))
    depths, uncertainties = np.stack(depths), np.stack(uncertainties)
    half = SIZE // KERNEL // 2
    bright_scatter, faint_scatter = (np.nanstd(depths[:, :, :half]), np.nanstd(depths[:, :, half:]))
    bright_error, faint_error = np.median(uncertainties[:, :, :half]), np.median(uncertainties[:, :, half:])
    assert faint_scatter > 3 * bright_scatter
    assert faint_error > 3 * bright_error
    # Where the noise decides (the faint half) the error is its scatter's size; the
    # bright half's depths scatter under the floor (a fiftieth of a step), and read so.
    assert faint_error == pytest.approx(faint_scatter, rel=0.5)
    step = WORKING_DISTANCES_UM[1] - WORKING_DISTANCES_UM[0]
    assert bright_error == pytest.approx(DEPTH_UNCERTAINTY_FLOOR_STEPS * step) and bright_scatter < bright_error
    assert np.all(uncertainties > 0) and np.all(np.isfinite(uncertainties))


def test_the_plane_weighs_kernels_by_their_uncertainty():
    """Kernels of one half ten times noisier than the other's: weighed by their
    uncertainties the slopes scatter less over draws than weighed alike; with an
    uncertainty that does not match the scatter (all alike in truth), the excess found by
    with_excess_scatter evens the weights out again and the standard errors are the
    scatter's."""
    from semservo.estimation.tilt import robust_plane, with_excess_scatter

    truth = plane_depths(2.0, -1.0)
    noise_um = np.where(np.indices(truth.shape)[1] < truth.shape[1] // 2, 0.02, 0.2)
    rng = np.random.default_rng(3)
    alike, weighed, calibrated = [], [], []
    for _ in range(40):
        depths = truth + rng.normal(0.0, 1.0, truth.shape) * noise_um
        alike.append(robust_plane(depths, KERNEL, PIXEL_UM).coefficients[1:])
        effective = with_excess_scatter(depths, noise_um, KERNEL, PIXEL_UM)
        weighed.append(robust_plane(depths, KERNEL, PIXEL_UM, uncertainties=effective).coefficients[1:])
        calibrated.append(np.median(effective / noise_um))
    assert np.all(np.std(weighed, axis=0) < 0.6 * np.std(alike, axis=0))
    assert np.median(calibrated) == pytest.approx(1.0, rel=0.3)  # the uncertainties were right: kept
    # Uncertainties that say nothing (all depths equally noisy, the claims 10 x apart):
    depths = truth + rng.normal(0.0, 0.05, truth.shape)
    effective = with_excess_scatter(depths, noise_um, KERNEL, PIXEL_UM)
    assert effective.max() / effective.min() < 1.5  # evened out, not 10 x apart
    assert np.median(effective) == pytest.approx(0.05, rel=0.3)  # and in depth, the scatter's size


def test_a_teach_summary_reads_errors_in_standard_errors_and_counts_refusals():
    """bench/teach.py's summary: the errors in their standard errors (RMS and largest) per
    tilt, the sweeps, and a refused teach counted, not averaged in."""
    from semservo.reproduce.tilts import summarize_teaches

    teaches = [{"error_deg": [0.02, -0.04], "uncertainty_deg": [0.02, 0.04], "z": [1.0, -1.0], "sweeps": 1},
               {"error_deg": [-0.06, 0.0], "uncertainty_deg": [0.02, 0.04], "z": [-3.0, 0.0], "sweeps": 3},
               {"refused": "the reference's focus sweep cannot tell the tilts"}]
    summary = summarize_teaches(teaches)
    assert summary["teaches"] == 3 and summary["refused"] == 1 and summary["sweeps_mean"] == 2.0
    assert summary["alpha"]["rms_z"] == pytest.approx(np.sqrt(5.0)) and summary["alpha"]["max_abs_z"] == 3.0
    assert summary["alpha"]["mean_error_deg"] == pytest.approx(-0.02)
    assert summary["beta"]["rms_z"] == pytest.approx(np.sqrt(0.5)) and summary["beta"]["mean_uncertainty_deg"] == 0.04
    everything_refused = summarize_teaches([{"refused": "no"}])
    assert everything_refused["refused"] == 1 and np.isnan(everything_refused["alpha"]["rms_z"])


# --------------------------------------------------------------------------------------
# A focus curve's centre read two ways: the mirror and the fitted symmetric curve


def noisy_curves(shape_of_peak, centre: float, kernels: int = 400, frames: int = 21, noise: float = 0.3,
                 pixels: int = 1024, seed: int = 1):
    """FocusCurves of ``kernels`` draws of one noise-free curve ``shape_of_peak(distance in
    samples from the centre)`` at sample ``centre``, with the measure's noise of
    :func:`focus_peak_uncertainties`' model, (2 N^2 + 4 S N) / pixels."""
    from semservo.estimation.tilt import FocusCurves

    rng = np.random.default_rng(seed)
    clean = shape_of_peak(np.arange(frames, dtype=float) - centre)[:, None] * np.ones((1, kernels))
    spread = np.sqrt((2 * noise**2 + 4 * clean * noise) / pixels)
    return FocusCurves(clean + rng.normal(size=clean.shape) * spread, np.full(clean.shape, noise), pixels)


def broad(distance):
    """A disc blur's curve: a round top, flanks 5-10 samples out (full width 15 samples)."""
    return 10.0 / (1.0 + (distance / 7.5) ** 2)


def cusp(distance):
    """A Gaussian probe whose width grows linearly: a cusp, half height 1.2 samples out."""
    return 10.0 / (1.0 + np.abs(distance) / 1.2) ** 2


def test_a_broad_focus_peak_is_read_from_its_flanks():
    """A broad, round-topped curve (a disc blur's), its centre between samples: the fitted
    reading scatters well under the mirror's, both unbiased, and its standard error is
    the scatter's size."""
    from semservo.estimation.tilt import clear_focus_peaks, fitted_centres

    curves = noisy_curves(broad, 10.3)
    fitted, errors = fitted_centres(curves)
    mirrored = clear_focus_peaks(curves, np.arange(21, dtype=float))
    assert np.isfinite(fitted).all() and np.isfinite(mirrored).all()
    assert np.std(fitted) < 0.6 * np.std(mirrored)
    assert abs(np.mean(fitted) - 10.3) < 4 * np.std(fitted) / np.sqrt(fitted.size)
    assert abs(np.mean(mirrored) - 10.3) < 4 * np.std(mirrored) / np.sqrt(mirrored.size)
    assert np.median(errors) == pytest.approx(np.std(fitted), rel=0.35)


def test_each_kernel_keeps_the_reading_its_noise_pins_better():
    """Half the kernels broad, half a faint cusp whose flanks sink into the noise within
    two samples: focus_peak_depths reads the broad ones by the fit and the cusps by the
    mirror (the fit cannot tell them), each unbiased, its standard errors the scatter's
    size."""
    from semservo.estimation.tilt import FocusCurves, focus_peak_depths, focus_peak_uncertainties, fitted_centres

    wide = noisy_curves(broad, 9.6, kernels=200)
    sharp = noisy_curves(lambda distance: cusp(distance) / 15, 9.6, kernels=200, seed=2)
    curves = FocusCurves(np.concatenate([wide.signal, sharp.signal], axis=1)[:, None, :],
                         np.concatenate([wide.noise, sharp.noise], axis=1)[:, None, :], 1024)
    distances = np.arange(21, dtype=float)
    depths, errors = (values[0] for values in focus_peak_depths(curves, distances))
    fitted_errors = fitted_centres(curves)[1][0]
    mirror_errors = focus_peak_uncertainties(curves, distances)[0]
    assert np.mean(fitted_errors[:200] < mirror_errors[:200]) > 0.9  # the broad ones: fitted
    assert np.isinf(fitted_errors[200:]).all()  # the faint cusps: mirrored
    for part in (slice(0, 200), slice(200, 400)):
        assert np.all(np.isfinite(depths[part]))
        assert abs(np.mean(depths[part]) - 9.6) < 4 * np.std(depths[part]) / np.sqrt(200)
        assert np.median(errors[part]) == pytest.approx(np.std(depths[part]), rel=0.5)


def test_a_cusp_is_read_as_well_by_the_fit_as_by_the_mirror():
    """A Gaussian probe's cusp is in the fitted family too (1 / measure, quadratic in
    |d - z|): fitted, its centre scatters no more than the mirror's, and the pull of where
    the peak falls between samples stays within the floor the tilts' standard errors
    keep for it (``SAMPLING_BIAS_STEPS``)."""
    from semservo.estimation.tilt import SAMPLING_BIAS_STEPS, FocusCurves, clear_focus_peaks, fitted_centres

    curves = noisy_curves(cusp, 9.6, seed=4)
    fitted = fitted_centres(curves)[0]
    assert np.std(fitted) <= np.nanstd(clear_focus_peaks(curves, np.arange(21, dtype=float)))
    for fraction in (0.0, 0.13, 0.25, 0.37, 0.5):
        clean = cusp(np.arange(21, dtype=float) - 9 - fraction)[:, None]
        centre = fitted_centres(FocusCurves(clean, np.full(clean.shape, 0.3), 1024))[0][0]
        assert abs(centre - 9 - fraction) < SAMPLING_BIAS_STEPS


def test_a_faint_curve_is_not_fitted():
    """Where too few samples about the peak stand over the noise, the fit does not tell
    (NaN, an infinite error), and the mirror's reading stands."""
    from semservo.estimation.tilt import fitted_centres

    faint = noisy_curves(lambda distance: 0.02 / (1.0 + np.abs(distance) / 1.2) ** 2, 10.0, kernels=50)
    centres, errors = fitted_centres(faint)
    assert np.isnan(centres).all() and np.isinf(errors).all()


def test_a_measurement_against_a_loose_teach_is_refused_where_both_together_miss_the_line():
    """The tilts a run acts on are a sweep's against the taught reading: where the two
    standard errors together exceed the line, the measurement is refused with the
    reason, and a run's pooling aims at what the teach leaves (line_against)."""
    from semservo.estimation.tilt import (MAX_TILT_UNCERTAINTY_DEG, TiltEstimate, line_against, measured_against,
                                          wants_another_sweep)

    def reading(uncertainty: float, sweeps: int = 1) -> TiltEstimate:
        return TiltEstimate(1.0, -2.0, 0.0, 40, 256, 0.01, 0.9, "", uncertainty, uncertainty, sweeps)

    tight, loose = reading(0.03), reading(0.08)
    assert line_against(tight) == pytest.approx(np.sqrt(MAX_TILT_UNCERTAINTY_DEG**2 - 0.03**2))
    assert line_against(loose) == pytest.approx(0.06)
    assert line_against(reading(MAX_TILT_UNCERTAINTY_DEG)) == 0.0
    pose = reading(0.07)
    assert measured_against(pose, tight) is pose  # together 0.076: measured
    refused = measured_against(pose, loose)  # together 0.106: not
    assert refused.confidence == 0.0 and np.isnan(refused.alpha_deg) and np.isnan(refused.beta_deg)
    assert "taught plane" in refused.reason and "0.11" in refused.reason and "0.06" in refused.reason
    assert refused.alpha_uncertainty_deg == 0.07  # its own, as the run's noise test needs
    # Pooling 4 could bring 0.07 to 0.035, under the 0.06 the loose teach leaves: swept again;
    # a sweep of 0.15 could not (0.075): refused at once.
    assert wants_another_sweep(refused, 4, line_against(loose))
    assert not wants_another_sweep(measured_against(reading(0.15), loose), 4, line_against(loose))


def test_a_teach_that_would_leave_its_runs_less_than_it_took_is_refused():
    """A teach pinned to worse than 0.1 / sqrt(2) degree is refused with the reason (its
    runs' sweeps would need to be pinned tighter than it), one within it is kept; a
    teach's pooling aims at that line and gives up at once where 4 sweeps cannot reach it."""
    from semservo.estimation.tilt import (MAX_TAUGHT_UNCERTAINTY_DEG, TiltEstimate, as_taught, line_against,
                                          wants_another_sweep)

    def reading(uncertainty: float, sweeps: int = 4) -> TiltEstimate:
        return TiltEstimate(0.1, -0.2, 0.0, 40, 256, 0.01, 0.9, "", uncertainty, uncertainty, sweeps)

    assert MAX_TAUGHT_UNCERTAINTY_DEG == pytest.approx(0.0707, abs=1e-4)
    kept = reading(0.065)
    assert as_taught(kept) is kept and line_against(kept) > 0.065
    refused = as_taught(reading(0.085))
    assert refused.confidence == 0.0 and np.isnan(refused.alpha_deg)
    assert "after 4 sweeps pooled" in refused.reason and "at most +-0.07" in refused.reason
    assert "+-0.05" in refused.reason  # what it would have left its runs
    assert wants_another_sweep(reading(0.12, sweeps=1), 4, MAX_TAUGHT_UNCERTAINTY_DEG)  # 0.06 in reach
    assert not wants_another_sweep(reading(0.16, sweeps=1), 4, MAX_TAUGHT_UNCERTAINTY_DEG)  # 0.08: hopeless


def test_the_gradient_measures_noise_constants_are_what_white_noise_does_to_it():
    """gradient_noise_constants: unit white noise's mean gradient energy (the gain) and how
    much more a kernel's mean of it scatters than independent pixels' would (the
    correlation), against 60 frames of white noise (seeded)."""
    from semservo.estimation.tilt import gradient_noise_constants

    gain, correlation = gradient_noise_constants(KERNEL)
    rng = np.random.default_rng(11)
    energies = []
    for _ in range(60):
        smooth = cv2.GaussianBlur(rng.normal(size=(SIZE, SIZE)).astype(np.float32), (0, 0), 1.0)
        energy = cv2.Sobel(smooth, cv2.CV_32F, 1, 0) ** 2 + cv2.Sobel(smooth, cv2.CV_32F, 0, 1) ** 2
        energies.append(energy.reshape(SIZE // KERNEL, KERNEL, SIZE // KERNEL, KERNEL).mean(axis=(1, 3)))
    energies = np.array(energies, dtype=np.float64)
    assert energies.mean() == pytest.approx(gain, rel=0.02)
    assert energies.var() * KERNEL * KERNEL / (2 * gain**2) == pytest.approx(correlation, rel=0.1)
    assert gradient_noise_constants(16)[1] < correlation  # fewer lags fit a smaller kernel


def test_the_gradient_measure_takes_the_noise_out_and_finds_each_kernels_depth():
    """gradient_focus_curves: white noise lands in the noise share (the scene's share is
    the same with and without it), a flat scene under noise shows no focus peak, and the
    depths of a tilted plane read by it are eq. 13's within a fraction of a step."""
    from semservo.estimation.tilt import (clear_focus_peaks, focus_measure_curves, gradient_focus_curves,
                                          kernel_depths)

    sweep = sweep_of_plane(0.0, 0.0)[:, :128, :128]
    rng = np.random.default_rng(4)
    noisy = sweep + rng.normal(0, 6.0, sweep.shape)
    clean, dirty = gradient_focus_curves(sweep, KERNEL), gradient_focus_curves(noisy, KERNEL)
    in_focus = np.argmax(clean.signal.mean(axis=(1, 2)))
    assert np.allclose(dirty.signal[in_focus], clean.signal[in_focus], rtol=0.2)
    assert dirty.pixels < KERNEL * KERNEL  # the smoothed noise is correlated
    flat = np.full((len(WORKING_DISTANCES_UM), SIZE, SIZE), 40.0) + rng.normal(0, 8.0, (len(WORKING_DISTANCES_UM),
                                                                                      SIZE, SIZE))
    assert np.isfinite(clear_focus_peaks(focus_measure_curves(flat, KERNEL, "gradient"), WORKING_DISTANCES_UM)).sum() <= 1
    tilted = sweep_of_plane(3.0, -2.0)
    step = WORKING_DISTANCES_UM[1] - WORKING_DISTANCES_UM[0]
    by_gradient = kernel_depths(tilted, WORKING_DISTANCES_UM, KERNEL, PIXEL_UM, measure="gradient").depths
    by_variance = kernel_depths(tilted, WORKING_DISTANCES_UM, KERNEL, PIXEL_UM).depths
    assert np.isfinite(by_gradient).all()
    assert np.median(np.abs(by_gradient - by_variance)) < 0.1 * step
    estimate = estimate_tilt(tilted, WORKING_DISTANCES_UM, PIXEL_UM, kernel=KERNEL, measure="gradient")
    assert estimate.alpha_deg == pytest.approx(3.0, abs=0.3) and estimate.beta_deg == pytest.approx(-2.0, abs=0.3)
    with pytest.raises(ValueError, match="unknown focus measure 'sobel'"):
        estimate_tilt(tilted, WORKING_DISTANCES_UM, PIXEL_UM, kernel=KERNEL, measure="sobel")


def test_curves_made_otherwise_are_read_as_kernel_depths_reads_a_sweeps():
    """depths_from_curves is kernel_depths' reading: the same depths and standard errors
    from the sweep's own curves, kernels left out are NaN, and a quiet sweep's curves
    with a noisy twin's noise share keep most kernels and read closer to the truth than
    the twin's own (the pull without the twin's noise, as bench/tilt_sampling.py reads)."""
    from semservo.estimation.tilt import (FocusCurves, depths_from_curves, focus_measure_curves, kernel_depths,
                                          noise_free_focus_curves)

    sweep = sweep_of_plane(2.0, -1.0)
    for measure in ("normalized_variance", "gradient"):
        direct = kernel_depths(sweep, WORKING_DISTANCES_UM, KERNEL, PIXEL_UM, measure=measure)
        read = depths_from_curves(sweep, focus_measure_curves(sweep, KERNEL, measure),
                                  noise_free_focus_curves(sweep, KERNEL), WORKING_DISTANCES_UM, KERNEL, PIXEL_UM)
        assert np.allclose(read.depths, direct.depths, equal_nan=True)
        assert np.allclose(read.uncertainties, direct.uncertainties, equal_nan=True)
    left_out = np.zeros(direct.depths.shape, dtype=bool)
    left_out[0, :] = True
    curves = noise_free_focus_curves(sweep, KERNEL)
    fewer = depths_from_curves(sweep, curves, curves, WORKING_DISTANCES_UM, KERNEL, left_out=left_out)
    assert np.isnan(fewer.depths[0]).all() and np.isfinite(fewer.depths[1:]).all()

    clean = sweep  # its noise (sd 1) next to the twin's (sd 12)
    twin = clean + np.random.default_rng(8).normal(0, 12.0, clean.shape)
    noisy = noise_free_focus_curves(twin, KERNEL)
    as_twin = depths_from_curves(clean, FocusCurves(noise_free_focus_curves(clean, KERNEL).signal, noisy.noise,
                                                    noisy.pixels), noisy, WORKING_DISTANCES_UM, KERNEL)
    twins_own = depths_from_curves(twin, noisy, noisy, WORKING_DISTANCES_UM, KERNEL)
    truth = plane_depths(2.0, -1.0)
    seen = np.isfinite(as_twin.depths)
    assert seen.sum() >= 0.5 * seen.size
    assert np.nanmedian(np.abs(as_twin.depths - truth)) < np.nanmedian(np.abs(twins_own.depths - truth))
