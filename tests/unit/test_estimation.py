"""semservo.estimation: the sign convention, sub-pixel accuracy on real SEM frames,
rotation, invariance to brightness and contrast, masks, confidence, SNR, bad input."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from PIL import Image

import semservo.estimation as estimation
from semservo.estimation import MotionEstimator, estimate_snr_db
from semservo.pairs import poisson_gaussian, shifted_pair


@pytest.fixture(scope="module")
def frame(recorded_run) -> np.ndarray:
    return np.asarray(Image.open(recorded_run / "frame10.png")).astype(np.float64)


@pytest.fixture(scope="module")
def reference_estimator(frame):
    return MotionEstimator(frame)


def rotated(image: np.ndarray, angle_deg: float) -> np.ndarray:
    """Content turned counter-clockwise as displayed (OpenCV's positive angle)."""
    rows, cols = image.shape
    matrix = cv2.getRotationMatrix2D(((cols - 1) / 2, (rows - 1) / 2), angle_deg, 1.0)
    return cv2.warpAffine(image.astype(np.float32), matrix, (cols, rows), flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT)


def test_sign_convention_of_the_contract(frame):
    # current[y, x] == reference[y, x - 3]  =>  dx == +3; likewise rows for dy.
    reference = frame[20:480, 20:480]
    current = frame[20 + 2:480 + 2, 20 - 3:480 - 3]  # current[y, x] = frame[y + 2, x - 3]
    np.testing.assert_array_equal(current[10, 13], reference[12, 10])
    motion = MotionEstimator(reference).estimate(current)
    assert motion.dx == pytest.approx(3, abs=0.02)
    assert motion.dy == pytest.approx(-2, abs=0.02)
    assert motion.rotation_deg == pytest.approx(0, abs=0.05)


def test_opencv_positive_angle_is_counter_clockwise_as_displayed():
    # Pins the meaning of the rotation the tests below build: a bright spot right of
    # the centre moves up (towards row 0) under a positive OpenCV angle.
    image = np.zeros((101, 101), np.float32)
    image[50, 80] = 1
    turned = rotated(image, 90)
    row, col = np.unravel_index(np.argmax(turned), turned.shape)
    assert (row, col) == (20, 50)


def fourier_shifted(image: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """``image`` with its content moved by exactly (dx, dy), periodically (phase ramp)."""
    rows, cols = image.shape
    v = np.fft.fftfreq(rows)[:, None]
    u = np.fft.fftfreq(cols)[None, :]
    return np.fft.ifft2(np.fft.fft2(image) * np.exp(-2j * np.pi * (u * dx + v * dy))).real


@pytest.mark.parametrize("precision", ["fast", "full"])
def test_known_subpixel_shifts_of_a_synthetic_texture(precision):
    """A smooth periodic random texture moved by exact sub-pixel amounts."""
    rng = np.random.default_rng(21)
    noise = rng.normal(0, 1, (256, 320))
    v, u = np.fft.fftfreq(256)[:, None], np.fft.fftfreq(320)[None, :]
    texture = np.fft.ifft2(np.fft.fft2(noise) * np.exp(-0.5 * (u**2 + v**2) / 0.08**2)).real  # smooth, periodic
    texture /= texture.std()
    reference = 100 + 20 * texture
    for dx, dy in [(0.5, 0.0), (-1.25, 2.75), (3.3, -0.1), (-7.61, 4.07)]:
        motion = MotionEstimator(reference, rotation=False, precision=precision).estimate(
            fourier_shifted(reference, dx, dy))
        assert motion.dx == pytest.approx(dx, abs=0.02) and motion.dy == pytest.approx(dy, abs=0.02)


#: Bounds per precision: (mean, max) error in px on clean and on moderately noisy pairs.
BOUNDS = {"full": {"clean": (0.02, 0.06), "noisy": (0.03, 0.1)},
          "fast": {"clean": (0.05, 0.12), "noisy": (0.05, 0.15)}}


@pytest.mark.parametrize("precision", ["fast", "full"])
@pytest.mark.parametrize("factor", [2, 3, 4])
def test_known_subpixel_shifts_of_real_frames(frame, factor, precision):
    """Halves, thirds and quarters, exact by block averaging (no interpolation)."""
    rng = np.random.default_rng(factor)
    errors = []
    for _ in range(6):
        dx, dy = rng.integers(-4 * factor, 4 * factor + 1, size=2) / factor
        pair = shifted_pair(frame, dx, dy, factor, margin=4 * factor)
        motion = MotionEstimator(pair.reference, rotation=False, precision=precision).estimate(pair.current)
        errors.append(np.hypot(motion.dx - dx, motion.dy - dy))
    mean_bound, max_bound = BOUNDS[precision]["clean"]
    assert np.mean(errors) < mean_bound and np.max(errors) < max_bound, errors


@pytest.mark.parametrize("precision", ["fast", "full"])
def test_known_shifts_with_moderate_sem_noise(frame, precision):
    rng = np.random.default_rng(11)
    errors = []
    for _ in range(10):
        dx, dy = rng.integers(-8, 9, size=2) / 2
        pair = shifted_pair(frame, dx, dy, 2, margin=8)
        reference = poisson_gaussian(pair.reference, 1000, 2, rng)
        current = poisson_gaussian(pair.current, 1000, 2, rng)
        motion = MotionEstimator(reference, rotation=False, precision=precision).estimate(current)
        errors.append(np.hypot(motion.dx - dx, motion.dy - dy))
    mean_bound, max_bound = BOUNDS[precision]["noisy"]
    assert np.mean(errors) < mean_bound and np.max(errors) < max_bound, errors


def test_unknown_precision_is_refused(frame):
    with pytest.raises(ValueError, match="precision"):
        MotionEstimator(frame, precision="ultra")


@pytest.mark.parametrize("angle", [0.3, -0.35, 0.4, -3.0, 12.5, -45.0, 90.0, 135.0, -170.0])
def test_rotation_about_the_beam(frame, reference_estimator, angle):
    motion = reference_estimator.estimate(rotated(frame, angle))
    assert motion.rotation_deg == pytest.approx(angle, abs=0.05)
    assert abs(motion.dx) < 0.1 and abs(motion.dy) < 0.1
    assert motion.confidence > 0.9


def test_rotation_then_translation_in_current_image_axes(frame):
    reference = frame[40:472, 40:472]
    turned = rotated(frame, 8.0)
    current = turned[40 - 5:472 - 5, 40 - 7:472 - 7]  # content moved right 7, down 5
    motion = MotionEstimator(reference).estimate(current)
    assert motion.rotation_deg == pytest.approx(8.0, abs=0.05)
    assert motion.dx == pytest.approx(7, abs=0.1)
    assert motion.dy == pytest.approx(5, abs=0.1)


@pytest.mark.parametrize("angle", [0.12, -0.4, 0.9, -6.0])
@pytest.mark.parametrize("precision", ["fast", "full"])
def test_turned_and_shifted_frames_give_the_shift_to_hundredths(frame, angle, precision):
    # The fast path turns back the halved image, "full" the whole one; both must hold
    # the translation accuracy under small and moderate turns.
    reference = frame[40:472, 40:472]
    turned = rotated(frame, angle)
    current = turned[40 - 4:472 - 4, 40 - 6:472 - 6]  # content moved right 6, down 4
    motion = MotionEstimator(reference, precision=precision).estimate(current)
    assert motion.rotation_deg == pytest.approx(angle, abs=0.05)
    assert motion.dx == pytest.approx(6, abs=0.05)
    assert motion.dy == pytest.approx(4, abs=0.05)


@pytest.mark.parametrize("angle", [0.01, -0.015])
def test_tiny_turns_are_reported_and_skipping_their_derotation_changes_nothing(frame, angle, monkeypatch):
    reference = frame[40:472, 40:472]
    turned = rotated(frame, angle)
    current = turned[40 - 3:472 - 3, 40 + 2:472 + 2]  # content moved left 2, down 3
    skipped = MotionEstimator(reference).estimate(current)
    monkeypatch.setattr(estimation.estimator, "DEROTATE_ABOVE_DEG", 0.0)
    derotated = MotionEstimator(reference).estimate(current)
    assert skipped.rotation_deg == pytest.approx(angle, abs=0.05)  # the rotation error floor
    assert skipped.dx == pytest.approx(derotated.dx, abs=0.01)
    assert skipped.dy == pytest.approx(derotated.dy, abs=0.01)
    assert skipped.dx == pytest.approx(-2, abs=0.08) and skipped.dy == pytest.approx(3, abs=0.08)


def blob_texture(turn_deg: float, size: int = 256, blobs: int = 1200) -> np.ndarray:
    """Gaussian blobs drawn analytically at positions turned by ``turn_deg`` (counter-
    clockwise as displayed): an exact rotation, with no interpolation anywhere."""
    rng = np.random.default_rng(7)
    positions = rng.uniform(-size * 0.75, size * 0.75, (blobs, 2))
    widths = rng.uniform(1.2, 4.0, blobs)
    heights = rng.uniform(-1, 1, blobs)
    turn = np.deg2rad(turn_deg)
    x = np.cos(turn) * positions[:, 0] + np.sin(turn) * positions[:, 1]
    y = -np.sin(turn) * positions[:, 0] + np.cos(turn) * positions[:, 1]
    centre = (size - 1) / 2
    image = np.zeros((size, size))
    for bx, by, width, height in zip(x, y, widths, heights):
        if abs(bx) < size / 2 + 12 and abs(by) < size / 2 + 12:
            # Each blob where it is above 1e-8 of its height (6 widths): the same image
            # to float32 precision, at a hundredth of the time of the whole grid.
            reach = 6 * width
            col_range = np.arange(max(0, int(centre + bx - reach)), min(size, int(centre + bx + reach) + 2))
            row_range = np.arange(max(0, int(centre + by - reach)), min(size, int(centre + by + reach) + 2))
            if col_range.size and row_range.size:
                cols, rows = col_range - centre, row_range - centre
                image[np.ix_(row_range, col_range)] += height * np.exp(
                    -((cols[None, :] - bx) ** 2 + (rows[:, None] - by) ** 2) / (2 * width**2))
    return (128 + 50 * image).astype(np.float32)


def test_small_turns_are_measured_not_locked_to_zero():
    # The magnitude spectrum is undersampled by the DFT, so a turn that moves every
    # radius by under a bin used to read as nearly zero (0.1 degree read 0.007).
    estimator = MotionEstimator(blob_texture(0.0, size=320))
    for turn in (0.05, -0.1, 0.2, -0.3, 0.6):
        assert estimator.estimate(blob_texture(turn, size=320)).rotation_deg == pytest.approx(turn, abs=0.03)


def test_brightness_and_contrast_changes_do_not_move_the_estimate(frame):
    pair = shifted_pair(frame, 2.5, -1.5, 2, margin=6)
    estimator = MotionEstimator(pair.reference)
    plain = estimator.estimate(pair.current)
    changed = estimator.estimate(np.clip(1.8 * pair.current + 40, 0, None))
    darker = estimator.estimate(0.4 * pair.current - 10)
    for motion in (changed, darker):
        assert motion.dx == pytest.approx(plain.dx, abs=0.01)
        assert motion.dy == pytest.approx(plain.dy, abs=0.01)
    assert plain.dx == pytest.approx(2.5, abs=0.03) and plain.dy == pytest.approx(-1.5, abs=0.03)


@pytest.mark.parametrize("shape", [(256, 384), (384, 200), (64, 96)])
def test_non_square_frames(frame, shape):
    rows, cols = shape
    reference = frame[50:50 + rows, 60:60 + cols]
    current = frame[50 - 3:50 - 3 + rows, 60 - 4:60 - 4 + cols]  # content moved right 4, down 3
    motion = MotionEstimator(reference).estimate(current)
    assert (motion.dx, motion.dy) == (pytest.approx(4, abs=0.08), pytest.approx(3, abs=0.08))
    assert motion.rotation_deg == pytest.approx(0, abs=0.1)


def test_integer_and_float_types_agree(frame):
    reference = frame[10:330, 10:330]
    current = frame[12:332, 7:327]
    results = []
    for dtype, scale in ((np.uint8, 1), (np.uint16, 257), (np.float32, 1 / 255)):
        estimator = MotionEstimator((reference * scale).astype(dtype), rotation=False)
        results.append(estimator.estimate((current * scale).astype(dtype)))
    for motion in results:
        assert motion.dx == pytest.approx(3, abs=0.02) and motion.dy == pytest.approx(-2, abs=0.02)


def test_mask_reference_from_a_thresholded_reference(frame):
    """Paper case 6: the taught image is a binary mask of the object, obtained by
    intensity thresholding; the live image is the real SEM frame."""
    mask = cv2.GaussianBlur(frame.astype(np.float32), (0, 0), 3) < frame.mean() - 25  # the dark gripper
    assert 0.1 < mask.mean() < 0.5
    estimator = MotionEstimator(frame, mask=mask)
    for dx, dy in [(9, -6), (-25, 14), (0, 0)]:
        motion = estimator.estimate(np.roll(np.roll(frame, dx, axis=1), dy, axis=0))
        assert motion.dx == pytest.approx(dx, abs=0.5) and motion.dy == pytest.approx(dy, abs=0.5)
        assert motion.rotation_deg == 0.0 and motion.confidence > 0.5


def test_a_mask_image_must_be_two_levels(frame):
    """binary_region: a mask image (the object white on black, its edges perhaps
    antialiased) is its pixels above the middle of its two levels; a grey picture given
    as a mask is refused, not read as 'every pixel above 0' (the CLI's old reading, which
    gave shifts larger than the image)."""
    from semservo.estimation.masks import binary_region

    mask = np.zeros((64, 64), np.uint8)
    mask[16:48, 16:48] = 255
    mask[16, 16:48] = 100  # an antialiased edge, darker than the middle
    region = binary_region(mask)
    assert region.sum() == 31 * 32 and not region[16, 20] and region[17, 20]
    assert binary_region(mask.astype(bool)).sum() == 32 * 32
    for picture, says in ((frame, "is not binary"), (np.full((64, 64), 9, np.uint8), "is not binary: 100%")):
        with pytest.raises(ValueError, match=says):
            binary_region(picture)


def test_mask_reference_from_clicked_corners_tracks_the_object(frame):
    """A rough outline from clicked corners defines the target position; the estimate
    moves with the object exactly as the object moves."""
    corners = [(70, 140), (130, 120), (160, 300), (230, 300), (290, 140), (320, 160), (300, 430), (100, 440)]
    estimator = MotionEstimator(frame, mask=corners)
    here = estimator.estimate(frame)
    moved = estimator.estimate(np.roll(np.roll(frame, 12, axis=1), -7, axis=0))
    assert moved.dx - here.dx == pytest.approx(12, abs=0.3)
    assert moved.dy - here.dy == pytest.approx(-7, abs=0.3)
    assert np.hypot(here.dx, here.dy) < 20  # the outline is roughly where the gripper is


def test_confidence_separates_matching_from_unrelated_images(frame, reference_estimator, recorded_run):
    rng = np.random.default_rng(0)
    matching = reference_estimator.estimate(np.roll(frame, 4, axis=0))
    noise = reference_estimator.estimate(rng.normal(128, 30, frame.shape))
    unrelated = MotionEstimator(frame[:256, :256], rotation=False).estimate(frame[256:, 256:])
    assert matching.confidence > 0.9
    assert noise.confidence < 0.3
    assert unrelated.confidence < 0.5
    assert matching.psr > 5 * noise.psr


def test_snr_follows_the_added_noise():
    rng = np.random.default_rng(3)
    # A smooth signal of known power plus white noise of known power.
    smooth = cv2.GaussianBlur(rng.normal(0, 1, (512, 512)).astype(np.float32), (0, 0), 4)
    smooth *= 10 / smooth.std()
    for noise_sigma, true_db in ((1.0, 20.0), (3.16, 10.0), (10.0, 0.0)):
        noisy = smooth + rng.normal(0, noise_sigma, smooth.shape).astype(np.float32)
        assert estimate_snr_db(noisy) == pytest.approx(true_db, abs=1.0)


def test_noisy_frames_are_filtered(frame):
    rng = np.random.default_rng(5)
    estimator = MotionEstimator(frame, rotation=False, snr_threshold_db=15)
    clean = estimator.estimate(np.roll(frame, 2, axis=1))
    noisy = estimator.estimate(poisson_gaussian(np.roll(frame, 2, axis=1), 100, 5, rng))
    assert clean.snr_db > noisy.snr_db
    assert noisy.snr_db < 15 and noisy.filtered
    assert noisy.dx == pytest.approx(2, abs=0.15)


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda f: f[:100, :120], "the reference is"),
        (lambda f: np.where(np.arange(f.size).reshape(f.shape) == 7, np.nan, f), "NaN"),
        (lambda f: np.array([]), "empty"),
        (lambda f: np.stack([f, f], axis=-1), "2-D"),
        (lambda f: f[:63, :63], "63 x 63"),
        (lambda f: f.astype(object), "pixel type"),
    ],
    ids=["other-shape", "nan", "empty", "three-d", "too-small", "object"],
)
def test_bad_input_is_a_clear_value_error(frame, reference_estimator, make, message):
    with pytest.raises(ValueError, match=message):
        reference_estimator.estimate(make(frame))


def test_bad_reference_is_a_clear_value_error(frame):
    with pytest.raises(ValueError, match="NaN"):
        MotionEstimator(np.full((64, 64), np.nan))
    with pytest.raises(ValueError, match="at least 64"):
        MotionEstimator(np.zeros((32, 128)))
    with pytest.raises(ValueError, match="at least 3 corner"):
        MotionEstimator(frame, mask=[(0, 0), (10, 10)])
    with pytest.raises(ValueError, match="part of the image"):
        MotionEstimator(frame, mask=np.zeros(frame.shape, bool))
    with pytest.raises(ValueError, match=r"flat \(every pixel 0\): there is nothing in it"):
        MotionEstimator(np.zeros((512, 512), np.uint8))  # a blank upload was taught; its run failed 10 s later


def test_fft_plans_are_kept_as_wisdom_on_disk(tmp_path, monkeypatch):
    monkeypatch.setattr(estimation.plans, "_wisdom_loaded", set())
    image = np.random.default_rng(0).normal(size=(72, 88))
    # The plans are already in this process's wisdom (as after any earlier test that
    # planned this shape): the file the setting names must be written all the same.
    monkeypatch.setenv("SEMSERVO_FFTW_WISDOM", str(tmp_path / "earlier.pickle"))
    MotionEstimator(image, rotation=False)
    path = tmp_path / "wisdom.pickle"
    monkeypatch.setenv("SEMSERVO_FFTW_WISDOM", str(path))
    MotionEstimator(image, rotation=False)
    assert path.is_file() and path.stat().st_size > 0


def test_the_package_exports_what_lab_scripts_use_and_motion_keeps_its_documented_fields():
    # README: Motion(dx, dy, rotation_deg, confidence, snr_db), in that order.
    import dataclasses

    from semservo.estimation import Motion

    assert [field.name for field in dataclasses.fields(Motion)][:5] == ["dx", "dy", "rotation_deg", "confidence",
                                                                        "snr_db"]
    for name in estimation.__all__:
        assert hasattr(estimation, name), name
    assert {"MotionEstimator", "Motion", "estimate_snr_db", "rotate_about_centre", "mask_reference",
            "polygon_mask", "as_image"} <= set(estimation.__all__)


def test_the_angle_refinement_parabola_finds_its_top_or_says_there_is_none():
    from semservo.estimation.rotation import probe_top

    # Correlations of a parabola peaking 0.25 probe above the middle, losing 1 % a probe.
    def correlation(probe: float) -> float:
        return 1.0 - 0.01 * (probe - 0.25) ** 2

    top = probe_top(correlation(-1), correlation(0), correlation(1))
    assert top.offset == pytest.approx(0.25)
    assert top.sharpness == pytest.approx(0.01, rel=1e-6)
    assert probe_top(0.9, 0.9, 0.9) is None  # flat: every turn looks alike
    assert probe_top(0.5, 0.7, 0.8) is None  # still rising: the top lies beyond the probes
    assert probe_top(0.9, 0.8, 0.9) is None  # a valley


def test_the_estimator_needs_no_private_call_before_any_public_one(frame):
    """Every public method works on a fresh estimator (the angle's refinement used to be
    public but worked only after a private call had halved the frame)."""
    public = [name for name in dir(MotionEstimator) if not name.startswith("_")]
    assert set(public) == {"estimate", "min_confidence", "prepare_rows", "learn_vibration", "vibration_sample"}
    motion = MotionEstimator(frame[:256, :256]).estimate(rotated(frame[:256, :256], 2.0))
    assert motion.rotation_deg == pytest.approx(2.0, abs=0.05)
    fresh = MotionEstimator(frame[:256, :256])
    fresh.prepare_rows(64)  # ahead of the partial frame it is for, on a fresh estimator
    assert fresh.estimate(rotated(frame[:256, :256], 2.0), first_row=64).rotation_deg == pytest.approx(2.0, abs=0.05)
    still = [np.roll(frame[:256, :256], shift, axis=1) for shift in (1, 2, 3)]
    kept, shifts = MotionEstimator(frame[:256, :256], rotation=False).vibration_sample(still)
    assert len(kept) == 3 and [round(dx) for dx, _ in shifts] == [1, 2, 3]
    # Learned on a fresh estimator: frames that do not vibrate teach no line.
    assert MotionEstimator(frame[:256, :256], rotation=False, scan_averaged=True).learn_vibration(still, 1e-3) == ()
    assert MotionEstimator(frame[:256, :256], rotation=False, scan_averaged=True).learn_vibration(
        still, 1e-3, cancelled=lambda: True) is None


def test_frames_far_below_6_db_are_filtered_by_default_and_clean_ones_are_not(frame):
    rng = np.random.default_rng(9)
    estimator = MotionEstimator(frame, rotation=False)
    assert not estimator.estimate(np.roll(frame, 2, axis=1)).filtered
    faint = frame.mean() + 0.2 * (frame - frame.mean())
    noisy = estimator.estimate(poisson_gaussian(np.roll(faint, 2, axis=1), 100, 2.0, rng))
    assert noisy.snr_db < estimation.DEFAULT_SNR_THRESHOLD_DB and noisy.filtered


def test_a_fit_that_runs_off_the_search_peak_is_brought_back():
    """The sub-pixel fit climbs a sidelobe of a noisy surface: the fit weighted by the
    prefilter is tried, then the search's own peak is kept."""
    from semservo.estimation.resolutions import MAX_FIT_MOVE_PX, kept_near
    from semservo.estimation.translation import Shift

    band, filtered_band = object(), object()
    start = Shift(4.2, -3.1)
    answers = {band: Shift(4.2 + 3 * MAX_FIT_MOVE_PX, -3.1), filtered_band: Shift(4.0, -3.3)}
    assert kept_near(start, answers.get, band, filtered_band) == Shift(4.0, -3.3)
    answers[filtered_band] = Shift(4.2, -3.1 - 3 * MAX_FIT_MOVE_PX)
    assert kept_near(start, answers.get, band, filtered_band) == start
    answers[band] = Shift(4.5, -2.7)
    assert kept_near(start, answers.get, band, filtered_band) == Shift(4.5, -2.7)


@pytest.mark.parametrize("contrast, electrons, least_acted_on", [(0.2, 100, 0), (0.5, 300, 3)])
def test_a_noisy_low_contrast_frame_gives_a_good_shift_or_a_refusal(recorded_run, contrast, electrons,
                                                                     least_acted_on):
    """A real frame at a fraction of its contrast and a low dose: at a fifth and 100
    electrons per grey level (-10 dB) nothing can be registered and everything is
    refused; at half and 300 (2 dB) most estimates are acted on, all of them good."""
    frame = np.asarray(Image.open(recorded_run / "frame20.png")).astype(np.float64)
    faint = frame.mean() + contrast * (frame - frame.mean())
    rng = np.random.default_rng(31)
    acted_on, errors = [], []
    for dx, dy in ((0.25, -2.0), (-2.5, 1.25), (3.0, 0.75), (-0.5, -3.5), (2.25, 2.5), (-3.25, -1.0)):
        pair = shifted_pair(faint, dx, dy, 4, margin=16)
        reference, current = (poisson_gaussian(image, electrons, 2.0, rng) for image in (pair.reference, pair.current))
        motion = MotionEstimator(reference, rotation=False).estimate(current)
        errors.append(np.hypot(motion.dx - dx, motion.dy - dy))
        if motion.confidence >= MotionEstimator.min_confidence:
            acted_on.append(errors[-1])
    assert len(acted_on) >= least_acted_on and all(error < 0.5 for error in acted_on), (acted_on, errors)
    if not least_acted_on:
        assert max(errors) > 1.0  # the case is hard: refusals, not luck
