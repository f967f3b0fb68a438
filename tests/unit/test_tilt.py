"""Tilts from focus (semservo.tilt): the focus measure (eq. 13), the depth per kernel,
the plane fit and its sign convention, against focus sweeps of known tilted planes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from semservo.tilt import estimate_tilt, focus_curves, focus_peaks, normalized_variance

SIZE, KERNEL, PIXEL_UM = 256, 32, 0.05
WORKING_DISTANCES_UM = np.linspace(-1.5, 1.5, 13)
#: Blur (px, standard deviation) per micrometre out of focus: a small depth of field.
BLUR_PX_PER_UM = 3.0


def texture(seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return 100 + 60 * cv2.GaussianBlur(rng.normal(size=(SIZE, SIZE)), (0, 0), 1.2)


def sweep_of_plane(alpha_deg: float, beta_deg: float, centre_um: float = 0.1, scene: np.ndarray | None = None,
                   seed: int = 5) -> np.ndarray:
    """Frames of a tilted plane at each working distance: each kernel blurred by its
    distance from focus at its centre (depth = centre + tan(alpha) y - tan(beta) x / cos(alpha),
    the module's convention), with shot-like noise."""
    scene = texture() if scene is None else scene
    rng = np.random.default_rng(seed)
    centres = (np.arange(SIZE // KERNEL) + 0.5) * KERNEL - SIZE / 2
    frames = []
    for distance in WORKING_DISTANCES_UM:
        frame = np.empty((SIZE, SIZE))
        blurred: dict[float, np.ndarray] = {}
        for row, y in enumerate(centres):
            for col, x in enumerate(centres):
                depth = (centre_um + np.tan(np.radians(alpha_deg)) * y * PIXEL_UM
                         - np.tan(np.radians(beta_deg)) / np.cos(np.radians(alpha_deg)) * x * PIXEL_UM)
                sigma = round(BLUR_PX_PER_UM * abs(depth - distance), 2)
                if sigma not in blurred:
                    blurred[sigma] = cv2.GaussianBlur(scene, (0, 0), sigma) if sigma > 0.05 else scene
                frame[row * KERNEL:(row + 1) * KERNEL, col * KERNEL:(col + 1) * KERNEL] = \
                    blurred[sigma][row * KERNEL:(row + 1) * KERNEL, col * KERNEL:(col + 1) * KERNEL]
        frames.append(frame + rng.normal(0, 1.0, frame.shape))
    return np.stack(frames)


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
