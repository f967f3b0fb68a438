"""The estimator on real SEM images of other instruments and samples (``../shared/data/
sem-images``), with its default settings: known sub-pixel shifts, turns, a scene whose
angle cannot be told, and the real drifted pair's self-consistency.

The bounds are several times the benchmark's means (``bench/sem_images.py``), so they
catch a method that breaks on such content, not noise in the last digit.
"""

from __future__ import annotations

import numpy as np
import pytest

from semservo.estimation import MotionEstimator, rotate_about_centre
from semservo.imagefiles import read_sem_image
from semservo.pairs import poisson_gaussian, shifted_pair

#: Scenes unlike the 2013 frames: a grid (JEOL), a smooth bright ring (TESCAN), a
#: low-contrast FIB-SEM slice, a hole at low magnification, round particles by a halo.
IMAGES = ("jeol_grid", "tescan_aperture", "fibsem_slice_cells", "hole_low_mag", "drift_pair_before")


def grey(pixels: np.ndarray) -> np.ndarray:
    pixels = pixels.astype(np.float64)
    return pixels / 257.0 if pixels.max() > 255 else pixels


def central_square(image: np.ndarray, side: int) -> np.ndarray:
    top, left = (image.shape[0] - side) // 2, (image.shape[1] - side) // 2
    return image[top:top + side, left:left + side]


@pytest.fixture(scope="module")
def images(sem_images) -> dict[str, np.ndarray]:
    return {name: grey(read_sem_image(sem_images / f"{name}.tif").pixels) for name in IMAGES}


@pytest.mark.parametrize("name", IMAGES)
def test_known_subpixel_shifts_under_sem_noise(images, name):
    rng = np.random.default_rng(sum(map(ord, name)))
    window = central_square(images[name], min(3 * 160 + 2 * 15, min(images[name].shape) // 3 * 3))
    errors = []
    for dx, dy in ((1 / 3, -2 / 3), (-4 / 3, 2.0), (3.0, 5 / 3), (-11 / 3, -7 / 3)):
        pair = shifted_pair(window, dx, dy, 3, margin=15)
        reference = poisson_gaussian(pair.reference, 1000, 2.0, rng)
        current = poisson_gaussian(pair.current, 1000, 2.0, rng)
        motion = MotionEstimator(reference, rotation=False).estimate(current)
        errors.append(np.hypot(motion.dx - dx, motion.dy - dy))
        assert motion.confidence >= MotionEstimator.min_confidence
    assert np.mean(errors) < 0.06 and max(errors) < 0.15, errors


@pytest.mark.parametrize("name", ["tescan_aperture", "hole_low_mag", "drift_pair_before"])
def test_turns_of_scenes_with_a_dominant_smooth_object(images, name):
    # These used to read as +-90 degrees or wander by tenths of a degree (the
    # magnitude spectrum is nearly isotropic); the image itself pins the angle.
    rng = np.random.default_rng(3)
    square = central_square(images[name], 384).astype(np.float32)
    estimator = MotionEstimator(poisson_gaussian(square, 1000, 2.0, rng))
    for turn in (-89.0, -7.5, -0.3, 0.4, 33.0, 120.0):
        motion = estimator.estimate(poisson_gaussian(rotate_about_centre(square, turn), 1000, 2.0, rng))
        assert motion.rotation_deg == pytest.approx(turn, abs=0.06)
        assert motion.confidence >= MotionEstimator.min_confidence


def test_a_scene_whose_angle_cannot_be_told_is_refused_not_guessed():
    # A disc and a ring: any turn looks the same. Their shift is well defined, their
    # angle is not, so the estimate must not be acted on.
    rng = np.random.default_rng(5)
    rows, cols = np.mgrid[:320, :320]
    radius = np.hypot(cols - 159.5, rows - 159.5)
    for scene in (np.where(radius < 90, 180.0, 40.0), 40.0 + 140.0 * ((radius > 50) & (radius < 100))):
        estimator = MotionEstimator(poisson_gaussian(scene, 1000, 2.0, rng))
        motion = estimator.estimate(poisson_gaussian(scene, 1000, 2.0, rng))
        assert motion.rotation_confidence < 0.3
        assert motion.confidence < MotionEstimator.min_confidence


def test_the_real_drifted_pair_is_self_consistent(sem_images):
    before = grey(read_sem_image(sem_images / "drift_pair_before.tif", data_bar=0).pixels)[:512, 8:-8]
    after = grey(read_sem_image(sem_images / "drift_pair_after.tif", data_bar=0).pixels)[:512, 8:-8]
    forward = MotionEstimator(before, rotation=False).estimate(after)
    backward = MotionEstimator(after, rotation=False).estimate(before)
    assert np.hypot(forward.dx + backward.dx, forward.dy + backward.dy) < 0.02
    # The drift between the two scans was (3, -5) px, as every method reads it.
    assert forward.dx == pytest.approx(3.0, abs=0.05) and forward.dy == pytest.approx(-5.0, abs=0.05)
