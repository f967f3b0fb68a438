"""The shift averaged over a scan's time (semservo.estimation.raster).

The frames here are not the simulated SEM's: a band-limited random texture is sampled
row by row at a position that oscillates in time (each row a snapshot, as a raster scan
under vibration draws it), by cubic interpolation, so the test checks the method on
distortions made another way than the simulator makes them.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from semservo.estimation import MotionEstimator, rotate_about_centre
from semservo.estimation.raster import (
    BAND_UNCERTAINTY_PX, ScanReference, band_shifts, predicted_frame, scan_averaged_shift, smoothed, vibration_lines,
)

SIZE = 256
MARGIN = 24


def texture(seed: int, envelope: bool) -> np.ndarray:
    """A band-limited texture larger than a frame; with ``envelope`` its contrast lies in
    the upper third of the rows (so a whole-frame correlation weights those rows most)."""
    rng = np.random.default_rng(seed)
    big = ndimage.gaussian_filter(rng.standard_normal((SIZE + 2 * MARGIN, SIZE + 2 * MARGIN)), 2.0)
    if envelope:
        rows = np.arange(big.shape[0])[:, None]
        big *= 0.15 + np.exp(-0.5 * ((rows - (MARGIN + SIZE / 5)) / (SIZE / 8)) ** 2)
    return 100 + 400 * big


def scanned(scene: np.ndarray, shift_x: np.ndarray, shift_y: np.ndarray) -> np.ndarray:
    """The frame whose row r shows the content moved by (shift_x[r], shift_y[r])."""
    rows, cols = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    coordinates = [rows + MARGIN - shift_y[:, None], cols + MARGIN - shift_x[:, None]]
    return ndimage.map_coordinates(scene, coordinates, order=3, mode="reflect")


def vibrating(scene, mean_x, mean_y, amplitude, cycles, phase):
    """A frame moved by (mean_x, mean_y) plus a vibration of ``cycles`` periods over the
    scan; returns it and the shift averaged over the scan's rows (the truth)."""
    time = np.arange(SIZE) / SIZE
    shift_x = mean_x + amplitude * np.sin(2 * np.pi * cycles * time + phase)
    shift_y = mean_y + amplitude * np.cos(2 * np.pi * cycles * time + 2 * phase)
    return scanned(scene, shift_x, shift_y), (shift_x.mean(), shift_y.mean())


def reference_of(scene):
    return scanned(scene, np.zeros(SIZE), np.zeros(SIZE))


def test_a_vibrating_scan_is_measured_where_the_sample_was_on_average_not_where_its_texture_was():
    whole_errors, averaged_errors = [], []
    for seed in range(6):
        scene = texture(seed, envelope=True)
        rng = np.random.default_rng(100 + seed)
        frame, truth = vibrating(scene, rng.uniform(-3, 3), rng.uniform(-3, 3), amplitude=0.4,
                                 cycles=rng.uniform(1.5, 3.0), phase=rng.uniform(0, 2 * np.pi))
        whole = MotionEstimator(reference_of(scene), rotation=False, snr_threshold_db=None).estimate(frame)
        averaged = MotionEstimator(reference_of(scene), rotation=False, snr_threshold_db=None,
                                   scan_averaged=True).estimate(frame)
        whole_errors.append(np.hypot(whole.dx - truth[0], whole.dy - truth[1]))
        averaged_errors.append(np.hypot(averaged.dx - truth[0], averaged.dy - truth[1]))
    # The whole frame sees the upper rows' moment; the bands' mean sees the scan's.
    assert np.mean(whole_errors) > 0.08
    assert np.mean(averaged_errors) < 0.3 * np.mean(whole_errors)
    assert max(averaged_errors) < 0.05


def test_a_still_frame_keeps_its_whole_frame_estimate_to_a_hundredth_of_a_pixel():
    scene = texture(7, envelope=False)
    for shift in ((0.25, -0.4), (5.5, 3.3), (-12.2, 0.0)):
        frame = scanned(scene, np.full(SIZE, shift[0]), np.full(SIZE, shift[1]))
        whole = MotionEstimator(reference_of(scene), rotation=False).estimate(frame)
        averaged = MotionEstimator(reference_of(scene), rotation=False, scan_averaged=True).estimate(frame)
        assert averaged.dx == pytest.approx(shift[0], abs=0.01) and averaged.dy == pytest.approx(shift[1], abs=0.01)
        assert abs(averaged.dx - whole.dx) < 0.02 and abs(averaged.dy - whole.dy) < 0.02
        assert averaged.confidence == whole.confidence


def test_a_turned_and_moved_frame_is_predicted_and_refined_in_the_estimators_convention():
    scene = texture(3, envelope=False)
    reference = reference_of(scene)
    frame = scanned(np.pad(rotate_about_centre(reference.astype(np.float32), 2.0), MARGIN, mode="reflect"),
                    np.full(SIZE, 1.5), np.full(SIZE, -2.25))
    motion = MotionEstimator(reference, rotation=True, scan_averaged=True).estimate(frame)
    assert motion.rotation_deg == pytest.approx(2.0, abs=0.05)
    assert motion.dx == pytest.approx(1.5, abs=0.05) and motion.dy == pytest.approx(-2.25, abs=0.05)
    # The prediction at the true motion matches the frame where it is known.
    ready = ScanReference.of(reference)
    predicted, known = predicted_frame(ready, 1.5, -2.25, 2.0)
    smooth_frame = ndimage.gaussian_filter(frame.astype(np.float32), 1.5)
    residue = np.abs(smooth_frame - predicted)[known]
    assert known.mean() > 0.8 and np.median(residue) < 0.05 * np.std(smooth_frame)


def test_bands_without_edges_are_left_out_and_a_frame_mostly_without_is_left_whole():
    scene = texture(5, envelope=False)
    reference = reference_of(scene)
    flat_below = reference.copy()
    flat_below[SIZE // 4:] = 100.0  # three quarters of the rows show nothing to register
    ready = ScanReference.of(flat_below)
    assert scan_averaged_shift(ready, flat_below, 0.0, 0.0) is None
    flat_band = reference.astype(np.float32).copy()
    flat_band[56:104] = 100.0  # band 2 (rows 64-95) and its smoothing's reach
    predicted, known = predicted_frame(ScanReference.of(flat_band), 0.0, 0.0)
    shifts, spreads, first_rows = band_shifts(smoothed(flat_band), predicted, known)
    assert list(first_rows[:4]) == [0, 32, 64, 96]
    assert not np.all(spreads[2] <= BAND_UNCERTAINTY_PX)  # the flat band pins nothing
    assert np.all(spreads[[0, 4, 5]] < 0.05)
    refined = scan_averaged_shift(ScanReference.of(flat_band), flat_band, 0.0, 0.0)
    assert refined.bands_used == len(first_rows) - 1 and np.isnan(refined.band_shifts[2]).all()


def test_a_correction_beyond_a_pixel_is_not_trusted():
    scene = texture(9, envelope=False)
    reference = reference_of(scene)
    frame = scanned(scene, np.full(SIZE, 4.0), np.zeros(SIZE))
    ready = ScanReference.of(reference)
    assert scan_averaged_shift(ready, frame, 4.0, 0.0).dx == pytest.approx(4.0, abs=0.01)
    assert scan_averaged_shift(ready, frame, 1.0, 0.0) is None  # three pixels off: not one linear step


def test_a_mask_reference_is_never_scan_averaged():
    scene = texture(2, envelope=False)
    reference = reference_of(scene)
    estimator = MotionEstimator(reference, rotation=False, mask=reference > np.median(reference), scan_averaged=True)
    assert estimator.scan_averaged is False


def test_a_pair_cut_from_one_scene_closes_forth_and_back_even_with_a_bright_border():
    # The real drift pair's shape: faint texture, a bright patch at one border, the two
    # scans an exact whole-pixel shift apart. The smoothing near a border sees the
    # border's reflection in one image and the scene in the other; left in, that residue
    # read as 0.2 px in the faint bands.
    rng = np.random.default_rng(11)
    big = 100 + 8 * ndimage.gaussian_filter(rng.standard_normal((SIZE + 16, SIZE + 16)), 1.5)
    rows, cols = np.mgrid[0:SIZE + 16, 0:SIZE + 16]
    big += 1000 * np.exp(-0.5 * (((cols - (SIZE + 6)) / 12.0) ** 2 + ((rows - SIZE * 0.7) / 30.0) ** 2))
    first, second = big[8:8 + SIZE, 8:8 + SIZE], big[3:3 + SIZE, 11:11 + SIZE]  # content moved by (-3, +5)
    forth = MotionEstimator(first, rotation=False, scan_averaged=True).estimate(second)
    back = MotionEstimator(second, rotation=False, scan_averaged=True).estimate(first)
    assert forth.dx == pytest.approx(-3.0, abs=0.015) and forth.dy == pytest.approx(5.0, abs=0.015)
    assert np.hypot(forth.dx + back.dx, forth.dy + back.dy) < 0.008  # with the border's residue: 0.017-0.019
    whole = MotionEstimator(first, rotation=False).estimate(second)
    assert abs(whole.dx + 3.0) > 0.05  # the whole frame's window weights the bright patch: -2.88


#: The tests' scan lasts 1 s: a row every 1 / SIZE s, frequencies in cycles a scan.
LINE_TIME_S = 1.0 / SIZE
LINES_HZ = (2.6, 17.4)


def tones(rng, mean_x, mean_y, wander: float = 0.0):
    """A frame of a scene vibrating at ``LINES_HZ`` (0.4 and 0.25 px, each axis its own
    phase, a fresh phase each frame: a line need not keep its phase from frame to frame)
    about (mean_x, mean_y); ``wander``: each line's phase also walks randomly along the
    scan (radians per sqrt(row)), a vibration that is not a steady tone. Returns the
    rows' shifts (x, y) and their mean over the scan (the truth)."""
    time = np.arange(SIZE) * LINE_TIME_S
    shifts = [np.full(SIZE, mean_x), np.full(SIZE, mean_y)]
    for frequency, amplitude in zip(LINES_HZ, (0.4, 0.25)):
        for axis in range(2):
            phase = rng.uniform(0, 2 * np.pi) + np.cumsum(rng.normal(0, wander, SIZE))
            shifts[axis] = shifts[axis] + amplitude * np.sin(2 * np.pi * frequency * time + phase)
    return shifts, (shifts[0].mean(), shifts[1].mean())


def test_vibration_lines_are_learned_at_rest_and_put_each_frame_where_the_sample_was_on_average():
    scene = texture(11, envelope=True)  # the upper rows hold the edges: their moment is not the scan's
    reference = reference_of(scene)
    rng = np.random.default_rng(5)
    at_rest = [scanned(scene, *tones(rng, 0.0, 0.0)[0]) for _ in range(4)]
    estimator = MotionEstimator(reference, rotation=False, snr_threshold_db=None, scan_averaged=True)
    learned = estimator.learn_vibration(at_rest, LINE_TIME_S)
    assert len(learned) == len(LINES_HZ)
    assert np.allclose(learned, LINES_HZ, atol=0.3)
    banded = MotionEstimator(reference, rotation=False, snr_threshold_db=None, scan_averaged=True)
    line_errors, band_errors = [], []
    for _ in range(6):
        shifts, truth = tones(rng, rng.uniform(-3, 3), rng.uniform(-3, 3))
        frame = scanned(scene, *shifts)
        fitted = estimator.estimate(frame, line_time_s=LINE_TIME_S)
        averaged = banded.estimate(frame, line_time_s=LINE_TIME_S)  # no lines learned: the bands' mean
        line_errors.append(np.hypot(fitted.dx - truth[0], fitted.dy - truth[1]))
        band_errors.append(np.hypot(averaged.dx - truth[0], averaged.dy - truth[1]))
    assert max(line_errors) < 0.03
    assert np.mean(line_errors) < 0.5 * np.mean(band_errors)
    # Without the scan's time per row the lines cannot be fitted: the bands' mean.
    assert estimator.estimate(frame).dx == pytest.approx(averaged.dx, abs=1e-9)


def test_lines_that_wander_a_little_still_help_and_a_still_stage_has_none():
    scene = texture(12, envelope=True)
    reference = reference_of(scene)
    rng = np.random.default_rng(8)
    # Tones whose phase walks ~0.3 radian over a scan (a line about a percent wide). At
    # ~1 radian a scan the fit is worse than the bands' mean (README: vibration lines).
    at_rest = [scanned(scene, *tones(rng, 0.0, 0.0, wander=0.02)[0]) for _ in range(4)]
    estimator = MotionEstimator(reference, rotation=False, snr_threshold_db=None, scan_averaged=True)
    assert len(estimator.learn_vibration(at_rest, LINE_TIME_S)) >= 1
    banded = MotionEstimator(reference, rotation=False, snr_threshold_db=None, scan_averaged=True)
    line_errors, band_errors = [], []
    for _ in range(6):
        shifts, truth = tones(rng, rng.uniform(-3, 3), rng.uniform(-3, 3), wander=0.02)
        frame = scanned(scene, *shifts)
        fitted, averaged = (method.estimate(frame, line_time_s=LINE_TIME_S) for method in (estimator, banded))
        line_errors.append(np.hypot(fitted.dx - truth[0], fitted.dy - truth[1]))
        band_errors.append(np.hypot(averaged.dx - truth[0], averaged.dy - truth[1]))
    assert np.mean(line_errors) < np.mean(band_errors)
    # Still frames with pixel noise only: no line stands out, and nothing is fitted.
    still = [reference + np.random.default_rng(seed).normal(0, 5, reference.shape) for seed in range(4)]
    ready = ScanReference.of(reference)
    assert vibration_lines(ready, still, [(0.0, 0.0)] * 4, LINE_TIME_S) == ()
    assert MotionEstimator(reference, rotation=False).learn_vibration(at_rest, LINE_TIME_S) == ()  # no scan averaging


def test_the_vibration_lines_threshold_is_scipys_chi_square_without_scipy():
    """``./dev up`` installs no scipy (only the OpenFIBSEM extra brings it): learning the
    vibration lines at a teach of several frames failed with "No module named 'scipy'"."""
    from scipy.special import chdtri

    from semservo.estimation.raster import chi_square_threshold

    for degrees_of_freedom in (4, 16, 64):
        for probability in (0.5, 1e-3, 1e-9):
            assert chi_square_threshold(degrees_of_freedom, probability) == pytest.approx(
                chdtri(degrees_of_freedom, probability), rel=1e-9)
    with pytest.raises(ValueError):
        chi_square_threshold(5, 0.01)


def corner_texture(seed: int) -> np.ndarray:
    """A band-limited texture whose contrast lies in one corner of the frame (a cluster of
    particles off the centre): the frame's rows there are few, so their vibration's shear
    does not average out over the texture."""
    rng = np.random.default_rng(seed)
    big = ndimage.gaussian_filter(rng.standard_normal((SIZE + 2 * MARGIN, SIZE + 2 * MARGIN)), 2.0)
    rows, cols = np.mgrid[0:big.shape[0], 0:big.shape[1]]
    corner = MARGIN + SIZE / 4
    big *= 0.15 + np.exp(-0.5 * (((rows - corner) ** 2 + (cols - corner) ** 2) / (SIZE / 10) ** 2))
    return 100 + 400 * big


def test_a_turn_is_measured_on_the_rows_moved_back_where_the_texture_lies_in_a_corner():
    """The vibration's wavy rows are a shear, which a whole-frame turn reads where the
    texture spans few rows; with the lines learned, the frame's rows are moved back by
    the lines fitted in it and the turn (and the shift at the centre, carried from the
    texture through the turn) measured again (``MotionEstimator._steadied``)."""
    scene = corner_texture(21)
    reference = reference_of(scene)
    rng = np.random.default_rng(9)
    at_rest = [scanned(scene, *tones(rng, 0.0, 0.0)[0]) for _ in range(4)]
    frames = [tones(rng, rng.uniform(-2, 2), rng.uniform(-2, 2)) for _ in range(6)]
    results = {}
    for steadied in (False, True):
        estimator = MotionEstimator(reference, rotation=True, snr_threshold_db=None, scan_averaged=True,
                                    steady_rows=steadied)
        learned = estimator.learn_vibration(at_rest, LINE_TIME_S)
        assert all(np.min(np.abs(np.asarray(learned) - line)) < 0.3 for line in LINES_HZ), learned
        turns, misses = [], []
        for shifts, truth in frames:
            motion = estimator.estimate(scanned(scene, *shifts), line_time_s=LINE_TIME_S)
            turns.append(motion.rotation_deg)
            misses.append(np.hypot(motion.dx - truth[0], motion.dy - truth[1]))
        results[steadied] = (np.sqrt(np.mean(np.square(turns))), np.sqrt(np.mean(np.square(misses))))
    (turn_before, shift_before), (turn_after, shift_after) = results[False], results[True]
    assert turn_after < 0.4 * turn_before, results
    assert shift_after < 0.6 * shift_before, results
    # A frame without vibration has nothing to move back: measured once, as before.
    still = estimator.estimate(scanned(scene, np.full(SIZE, 0.5), np.full(SIZE, -0.5)), line_time_s=LINE_TIME_S)
    assert abs(still.rotation_deg) < 0.01 and np.hypot(still.dx - 0.5, still.dy + 0.5) < 0.02
