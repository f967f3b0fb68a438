"""Focus sweeps whose content moved while they scanned (drift, the stage's x, y moves):
each frame moved back by how far its content had moved, read off the live frames
(semservo.estimation.tilt.content_shifts, steady_sweep; the estimator's track)."""

from __future__ import annotations

import numpy as np
import pytest

from semservo.estimation.tilt import (MIRRORED_KERNEL_FRACTION, content_shifts, estimate_tilt, mirrored_kernels,
                                      plan_sweep, steady_sweep)
from semservo.focus_sweeps import DefocusModel, TiltedTexture
from semservo.imagefiles import read_sem_image
from semservo.wire import Frame, frame_header
from services.estimator.core import EstimatorCore


def texture(rows: int, cols: int, seed: int = 3) -> np.ndarray:
    """Smoothed white noise, contrast 40 about 100."""
    noise = np.random.default_rng(seed).normal(0, 1, (rows, cols))
    blur = np.exp(-2 * np.pi**2 * 1.5**2 * (np.fft.fftfreq(rows)[:, None] ** 2 + np.fft.fftfreq(cols)[None, :] ** 2))
    smooth = np.real(np.fft.ifft2(np.fft.fft2(noise) * blur))
    return (100 + 40 * smooth / smooth.std()).astype(np.float32)


def test_a_frame_is_moved_back_by_its_contents_move():
    base = texture(200, 240)
    moved = np.zeros_like(base)
    moved[2:, 3:] = base[:-2, :-3]  # content moved right by 3 px and down by 2
    steadied = steady_sweep(np.stack([base, moved, base]), [[0, 0], [3, 2], [0, 0]])
    assert steadied.dtype == np.float32
    assert np.array_equal(steadied[0], base) and np.array_equal(steadied[2], base)  # unmoved frames untouched
    # Away from the edges the moved frame is the unmoved one again, to rounding.
    assert np.abs(steadied[1] - base)[8:-8, 8:-8].max() < 1e-3
    # Fractions of a pixel: there and back again, nothing smoothed on the way (but within
    # a few pixels of the edges, where the pixels moved out were replaced by their mirror).
    there = steady_sweep(base[None], [[0.37, -0.61]])
    back = steady_sweep(there, [[-0.37, 0.61]])
    assert np.abs(back[0] - base)[16:-16, 16:-16].max() < 0.1  # of a contrast of 40
    assert there[0][8:-8, 8:-8].std() == pytest.approx(base[8:-8, 8:-8].std(), rel=0.02)


def test_moves_that_are_not_one_per_frame_or_not_finite_are_refused():
    sweep = np.stack([texture(64, 64)] * 3)
    for shifts in ([[0, 0], [1, 1]], [[0, 0], [np.nan, 0], [0, 0]], [[0, 0], [40, 0], [0, 0]]):
        with pytest.raises(ValueError, match="content shifts"):
            steady_sweep(sweep, shifts)


def test_the_moves_are_read_off_the_live_frames_from_the_sweeps_middle_frame():
    # The content drifts 0.1 px right and 0.05 px up per second; live frames every second.
    track_times = np.arange(0.0, 30.0)
    shifts = content_shifts([10.5, 12.5, 14.5], track_times, 0.1 * track_times, -0.05 * track_times)
    assert shifts == pytest.approx(np.array([[-0.2, 0.1], [0.0, 0.0], [0.2, -0.1]]))
    # In any order, duplicates as one.
    order = np.r_[np.arange(29, -1, -1), 3]
    assert content_shifts([10.5, 12.5, 14.5], track_times[order], 0.1 * track_times[order],
                          -0.05 * track_times[order]) == pytest.approx(shifts)
    # A frame a spacing or less beyond the track: its last position; further, unknown.
    assert content_shifts([29.0, 29.9, 30.0], track_times, track_times, track_times)[2, 0] == pytest.approx(0.0)
    assert content_shifts([28.0, 29.0, 31.5], track_times, track_times, track_times) is None
    assert content_shifts([0.5, 1.0], [1.0], [0.0], [0.0]) is None  # one live frame is no track
    # One wrong live estimate (a repeated pattern read a period off) is not followed; a
    # stage's step is.
    wrong = 0.1 * track_times
    wrong[12] += 25.0
    # (Read as its neighbour there: a frame's drift, 0.1 px, off, not 25.)
    assert content_shifts([10.5, 12.0, 14.5], track_times, wrong, 0 * track_times) == pytest.approx(
        np.array([[-0.15, 0.0], [0.0, 0.0], [0.25, 0.0]]), abs=0.11)
    step = np.where(track_times < 12, 0.0, 8.0)
    assert content_shifts([10.0, 11.0, 14.0], track_times, step, step)[2] == pytest.approx([8.0, 8.0])


def test_border_kernels_are_left_out_where_mirrored_pixels_would_fill_an_eighth_of_them():
    limit = MIRRORED_KERNEL_FRACTION * 32
    # Content that moved right (and back left again) by up to the limit: every kernel kept.
    assert not mirrored_kernels([[-limit, 0], [0, 0], [limit, 0]], (512, 512), 32).any()
    # Beyond it, to the right: the last column's kernels only; up, beyond it: the first row's.
    left_out = mirrored_kernels([[0, -(limit + 1)], [0, 0], [limit + 1, 0]], (512, 512), 32)
    expected = np.zeros((16, 16), bool)
    expected[:, -1] = expected[0, :] = True
    assert np.array_equal(left_out, expected)


@pytest.fixture(scope="module")
def hole(sem_images) -> np.ndarray:
    return read_sem_image(sem_images / "hole_low_mag.tif").pixels.astype(np.float64)


def test_a_sweep_that_drifted_reads_its_tilts_as_a_still_one_once_steadied(hole):
    # A real texture (a hole in a membrane) on a plane at (-1, 3) degrees, under a
    # Gaussian probe written apart from the simulator; the sample drifts 0.3 px to the
    # right per frame (4 px over the sweep): drifting, its tilts read 0.3 degree off in
    # beta; moved back, as the still sweep does.
    size, margin, pixel_um = 512, 24, 0.05
    plane = TiltedTexture(hole, DefocusModel("gaussian", 2.5), pixel_um, shape=(size + 2 * margin,) * 2,
                          pose=(-1.0, 3.0, 0.0))
    distances = plan_sweep(0.0, 2.5, size * pixel_um, max_tilt_deg=5)
    frames = len(distances)
    moves = np.round(np.arange(frames) * 0.3).astype(int)
    shifts = np.column_stack([moves - moves[frames // 2], np.zeros(frames)])
    for seed in (0, 1):
        scanned = plane.sweep(distances, np.random.default_rng(seed))
        still = scanned[:, margin:margin + size, margin:margin + size]
        drifted = np.stack([frame[margin:margin + size, margin - move:margin - move + size]
                            for frame, move in zip(scanned, moves)])
        read_still = estimate_tilt(still, distances, pixel_um)
        read_drifted = estimate_tilt(drifted, distances, pixel_um)
        read_steadied = estimate_tilt(drifted, distances, pixel_um, content_shifts_px=shifts)
        assert abs(read_drifted.beta_deg - read_still.beta_deg) > 0.15
        assert abs(read_steadied.beta_deg - read_still.beta_deg) < 0.05
        assert abs(read_steadied.alpha_deg - read_still.alpha_deg) < 0.05


def live_frame(pixels: np.ndarray, seq: int, middle_ns: int) -> Frame:
    return Frame(frame_header(pixels, seq=seq, scan_started_at_ns=middle_ns - 1000, acquired_at_ns=middle_ns + 1000,
                              pixel_size_nm=100.0, magnification=1000.0, dwell_ns=720.0, source="test"), pixels)


def test_the_estimator_steadies_a_sweep_by_the_live_frames_it_measured_meanwhile():
    base = texture(288, 288)
    core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE")
    core.process(live_frame(base[16:272, 16:272], 0, 1_700_000_000_000_000_000))
    core.teach_latest(frames=1)
    second, start = 1_000_000_000, 1_700_000_000_000_000_000
    # Live frames over 10 s while the content drifts right by 0.4 px/s (whole pixels, for an
    # exact texture): the track knows where the content was at each time.
    for index in range(11):
        move = round(0.4 * index)
        core.process(live_frame(base[16:272, 16 - move:272 - move], index + 1, start + index * second))
    assert len(core.content_track) == 11
    sweep = np.stack([base[16:272, 16:272]] * 5)
    distances = [0.0, 1.0, 2.0, 3.0, 4.0]
    core.sweep_depths(sweep, distances, 100.0, frame_times_ns=[start + second * t for t in (1, 3, 5, 7, 9)])
    # The frames at 1 and 9 s saw the content 0 and 4 px to the right (0.4 px/s, in whole pixels).
    assert core.last_sweep_moved_px == pytest.approx(4.0, abs=0.01)
    assert core.counters["sweeps_steadied"] == 1
    # Beyond the live frames, or without frame times: read as scanned, and said so.
    core.sweep_depths(sweep, distances, 100.0, frame_times_ns=[start + second * t for t in (30, 31, 32, 33, 34)])
    assert core.last_sweep_moved_px is None and core.counters["sweeps_not_steadied"] == 1
    core.sweep_depths(sweep, distances, 100.0)
    assert core.last_sweep_moved_px is None and core.counters["sweeps_not_steadied"] == 2
    # A new reference starts its own track.
    core.teach_latest(frames=1)
    assert len(core.content_track) == 0
