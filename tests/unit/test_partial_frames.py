"""Partial frames: the rows of a scan scanned after a move settled, measured and acted on
a scan sooner than the next whole frame (the estimator's ``first_row``, its ``moved``
command, the controller's gate, the position law's aim, the in-process loop)."""

from __future__ import annotations

import math
from collections import deque

import cv2
import numpy as np
import pytest

from semservo.control import ControlLaw, PositionLaw
from semservo.estimation import MotionEstimator
from semservo.estimation.raster import BAND_ROWS, PARTIAL_FRAME_FROM, rows_scanned_after
from semservo.messages import MotionEstimate
from semservo.protocol.controller import RunSettings
from semservo.reproduce import loop
from semservo.wire import Frame, frame_header
from services.controller.run import Run, gate, uses_partial_frames
from services.estimator.core import EstimatorCore


def texture(size: int = 800, seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.normal(0, 1, (size, size)).astype(np.float32), (0, 0), 2.5)
    return (100 + 40 * base / base.std()).astype(np.float32)


def view(scene: np.ndarray, turn_deg: float = 0.0, dx: float = 0.0, dy: float = 0.0, size: int = 512) -> np.ndarray:
    """The scene's middle ``size`` square, its content turned counter-clockwise (as
    displayed) about the view's centre and moved by (dx, dy) px."""
    margin = (scene.shape[0] - size) // 2
    centre = (margin + (size - 1) / 2, margin + (size - 1) / 2)
    matrix = cv2.getRotationMatrix2D(centre, turn_deg, 1.0)
    matrix[:, 2] += (dx, dy)
    moved = cv2.warpAffine(scene, matrix, scene.shape[::-1], flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return moved[margin:margin + size, margin:margin + size]


def test_the_rows_after_a_move_are_a_band_s_start_and_at_least_half_the_scan():
    # 512 rows scanned over 0.512 s: a row per millisecond.
    assert rows_scanned_after(512, 1.0, 1.512, 0.9) == 0, "scanned wholly after it: the whole frame"
    assert rows_scanned_after(512, 1.0, 1.512, 1.6) is None, "scanned before it: no row"
    assert rows_scanned_after(512, 1.0, 1.512, 1.010) == BAND_ROWS, "row 10 rounded up to the band's start"
    assert rows_scanned_after(512, 1.0, 1.512, 1.032) == BAND_ROWS
    assert rows_scanned_after(512, 1.0, 1.512, 1.0321) == 2 * BAND_ROWS
    assert rows_scanned_after(512, 1.0, 1.512, 1.0 + 0.512 * PARTIAL_FRAME_FROM) == 256
    assert rows_scanned_after(512, 1.0, 1.512, 1.0 + 0.512 * PARTIAL_FRAME_FROM + 0.001) is None, "under half"
    assert rows_scanned_after(512, None, 1.5, 1.2) is None and rows_scanned_after(512, 1.5, 1.0, 1.2) is None


@pytest.mark.parametrize("turn_deg, dx, dy", [(0.0, 3.3, -2.2), (2.0, 3.3, -2.2), (-3.0, 10.4, 5.1)])
def test_a_partial_frame_measures_the_motion_its_rows_show_about_the_frames_centre(turn_deg, dx, dy):
    scene = texture()
    estimator = MotionEstimator(view(scene), rotation=True, scan_averaged=True, fft_effort="FFTW_ESTIMATE")
    noise = np.random.default_rng(1).normal(0, 2, (512, 512)).astype(np.float32)
    still = view(scene, turn_deg, dx, dy) + noise
    # The rows above were scanned while the stage still moved: 1.8 px from where it came to rest.
    landing = still.copy()
    landing[:100] = view(scene, turn_deg, dx - 1.5, dy + 1.0)[:100] + noise[:100]
    settled = estimator.estimate(still)
    partial = estimator.estimate(landing, first_row=100)
    blend = estimator.estimate(landing)
    assert partial.first_row == 128, "rounded up to a band's start"
    assert partial.confidence >= 0.5
    assert abs(settled.dx - dx) < 0.06 and abs(settled.dy - dy) < 0.06, "the views are made as meant"
    assert abs(partial.dx - settled.dx) < 0.01 and abs(partial.dy - settled.dy) < 0.01
    assert abs(partial.rotation_deg - settled.rotation_deg) < 0.005, "the turn about the frame's centre too"
    assert math.hypot(blend.dx - settled.dx, blend.dy - settled.dy) > 0.1, "the whole frame, a blend, is off"
    with pytest.raises(ValueError, match="at least 64"):
        estimator.estimate(landing, first_row=480)


def shaded_part(offset: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """A bright bar on a dark ground, its left edge brightened and its right edge shadowed
    (a detector on one side): a threshold's edges are not where a correlation puts it."""
    rows, cols = np.mgrid[0:256, 0:256].astype(np.float32)
    x, y = cols - offset[0], rows - offset[1]

    def ramp(distance):  # 0 outside, 1 inside, a 1.5 px edge
        return np.clip(distance / 1.5 + 0.5, 0.0, 1.0)
    inside = ramp(x - 80) * ramp(170 - x) * ramp(y - 60) * ramp(200 - y)
    along = (y > 60) & (y < 200)
    halo = 10 * np.exp(-((x - 80) / 3) ** 2) * along - 5 * np.exp(-((x - 170) / 4) ** 2) * along
    return (40 + 120 * inside + halo).astype(np.float32)


def test_a_partial_frame_against_a_mask_is_anchored_row_by_row_or_not_measured():
    """Cut at a row, a mask's correlation with the image moves (here by about 0.6 px):
    each band of an anchored mask is anchored to the image's same rows; a mask taken as
    drawn is measured on whole frames only."""
    image = shaded_part()
    anchored = MotionEstimator(image, mask=image > 100, fft_effort="FFTW_ESTIMATE")
    for first_row in (64, 96, 128):
        at_rest = anchored.estimate(image, first_row=first_row)
        assert abs(at_rest.dx) < 1e-3 and abs(at_rest.dy) < 1e-3
        moved = anchored.estimate(shaded_part((2.5, -1.5)), first_row=first_row)
        assert abs(moved.dx - 2.5) < 0.1 and abs(moved.dy + 1.5) < 0.1
    as_drawn = MotionEstimator(image, mask=np.roll(image > 100, 4, axis=1), fft_effort="FFTW_ESTIMATE")
    with pytest.raises(ValueError, match="whole frames"):
        as_drawn.estimate(image, first_row=64)
    as_drawn.prepare_rows(64)  # nothing to prepare: no error


def test_row_estimators_are_kept_for_the_last_few_bands_only():
    from semservo.estimation.estimator import ROW_ESTIMATORS_KEPT

    scene = texture(700)
    estimator = MotionEstimator(view(scene), rotation=False, fft_effort="FFTW_ESTIMATE")
    for band in range(1, ROW_ESTIMATORS_KEPT + 4):
        estimator.prepare_rows(band * BAND_ROWS)
    assert len(estimator._rows_estimators) == ROW_ESTIMATORS_KEPT
    assert (BAND_ROWS, False) not in estimator._rows_estimators, "the least recently used went first"


@pytest.mark.parametrize("alpha, beta", [(5.0, 5.0), (15.0, 15.0), (-15.0, 15.0), (15.0, -3.0), (0.3, 0.1)])
def test_a_frame_seen_square_on_reads_only_rows_after_the_move_from_the_row_said(alpha, beta):
    """Undoing a tilt's foreshortening resamples rows from above: the partial frame starts
    where no row scanned before the move reaches."""
    from semservo.estimation.tilt import rows_seen_square_on, undo_foreshortening

    for first_row in (64, 128, 256, 300):
        before = np.zeros((512, 512), np.float32)
        before[:first_row] = 1000.0  # scanned while the stage still moved
        reached = np.nonzero(np.abs(undo_foreshortening(before, alpha, beta)).max(axis=1) > 1e-3)[0]
        safe = rows_seen_square_on(first_row, (512, 512), alpha, beta)
        assert first_row <= safe and safe > reached.max()
        assert safe - reached.max() <= 4, "and not much later"


def test_a_mask_drawn_on_the_reference_s_object_is_anchored_to_it_and_one_drawn_elsewhere_is_not():
    image = shaded_part()
    threshold = image > 100
    anchored = MotionEstimator(image, mask=threshold, fft_effort="FFTW_ESTIMATE")
    raw = anchored.mask_offset
    assert 0.01 < math.hypot(*raw) <= 0.5, "the shading moves the mask's correlation off its threshold's edges"
    at_rest = anchored.estimate(image)
    assert abs(at_rest.dx) < 1e-3 and abs(at_rest.dy) < 1e-3, "the reference's own pose is the target"
    moved = anchored.estimate(shaded_part((2.5, -1.5)))
    assert abs(moved.dx - 2.5) < 0.05 and abs(moved.dy + 1.5) < 0.05
    elsewhere = MotionEstimator(image, mask=np.roll(threshold, 4, axis=1), fft_effort="FFTW_ESTIMATE")
    assert elsewhere.mask_offset == (0.0, 0.0), "a mask 4 px off the object is a target elsewhere, as drawn"
    assert elsewhere.estimate(image).dx == pytest.approx(-4, abs=0.3)


def timed_frame(pixels: np.ndarray, seq: int, started_ns: int, lasted_ns: int, timed: bool = True) -> Frame:
    header = frame_header(pixels, seq=seq, acquired_at_ns=started_ns + lasted_ns, pixel_size_nm=100.0,
                          magnification=1000.0, dwell_ns=720.0, source="test", scan_started_at_ns=started_ns,
                          source_interval_s=(started_ns / 1e9, (started_ns + lasted_ns) / 1e9) if timed else None)
    return Frame(header, pixels)


def test_the_estimator_measures_the_frame_a_move_settled_in_on_its_rows_after_it():
    scene = texture(700)
    core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE")
    lasted = 512_000_000  # a row per millisecond
    core.process(timed_frame(view(scene), 0, 0, lasted))
    core.teach_latest()
    assert core.moved(2 * lasted + 100_000_000) == {"partial_from_ns": 2 * lasted + 100_000_000}
    before = core.process(timed_frame(view(scene), 1, lasted, lasted))
    assert before.first_row == 0 and before.rows_scanned_from_ns is None, "scanned before the move: whole, stale"
    landed = view(scene, 0.0, 4.0, -3.0)
    landed[:100] = view(scene, 0.0, 1.0, 0.5)[:100]  # the stage still moving
    partial = core.process(timed_frame(landed, 2, 2 * lasted, lasted))
    assert partial.first_row == 128 and partial.rows_scanned_from_ns == 2 * lasted + 128_000_000
    assert partial.rows_source_interval_s == pytest.approx((2 * lasted / 1e9 + 0.128, 3 * lasted / 1e9))
    assert abs(partial.dx_px - 4.0) < 0.05 and abs(partial.dy_px + 3.0) < 0.05
    after = core.process(timed_frame(view(scene, 0.0, 4.0, -3.0), 3, 3 * lasted, lasted))
    assert after.first_row == 0, "scanned wholly after the move: the whole frame"
    core.moved(4 * lasted + 100_000_000)
    untimed = core.process(timed_frame(landed, 4, 4 * lasted, lasted, timed=False))
    assert untimed.first_row == 0, "a source that does not time its scans gives whole frames"
    core.moved(5 * lasted + 300_000_000)
    late = core.process(timed_frame(landed, 5, 5 * lasted, lasted))
    assert late.first_row == 0 and late.rows_scanned_from_ns is None, \
        "under half its rows after the move: whole (and stale, its scan began before the move settled)"


def make_run(**settings) -> Run:
    return Run(id="r", reference_id="ref", settings=RunSettings(**settings), started_at_ns=0, stage_at_start={},
               law=ControlLaw(("x", "y")), last_command_ns=1_000_000, recent=deque())


def estimate(started_ns: int, rows_from_ns: int | None = None) -> MotionEstimate:
    return MotionEstimate(seq=1, reference_id="ref", dx_px=1.0, dy_px=0.0, rotation_deg=0.0, confidence=0.9,
                          snr_db=20.0, filtered=False, pixel_size_nm=100.0, frame_acquired_at_ns=started_ns + 500_000,
                          frame_published_at_ns=started_ns + 600_000, frame_scan_started_at_ns=started_ns,
                          published_at_ns=started_ns + 700_000, estimation_ms=1.0, latency_ms=1.0,
                          first_row=128 if rows_from_ns else 0, rows_scanned_from_ns=rows_from_ns)


def test_the_gate_takes_a_partial_frame_whose_rows_began_after_the_move_as_fresh():
    run = make_run()
    assert gate(run, estimate(900_000)).action.startswith("held: stale")
    assert gate(run, estimate(900_000, rows_from_ns=1_000_500)) is None
    assert gate(run, estimate(900_000, rows_from_ns=999_000)).action.startswith("held: stale")
    assert uses_partial_frames(RunSettings()) and not uses_partial_frames(RunSettings(law="paper"))
    assert uses_partial_frames(RunSettings(law="paper", partial_frames=True))
    assert not uses_partial_frames(RunSettings(partial_frames=False))


def test_on_partial_frames_the_position_law_aims_at_the_rest_of_the_scan_its_move_lands_in():
    """After a move, the next frame measured is the rest of the scan the move lands in: its
    middle is about a frame sooner than the next whole scan's (1 s scans here, back to
    back, the move written 50 ms after a frame). The law aims its move at where the drift
    will have taken the content by then: by about a frame's drift less."""
    moves, drifts = [], []
    for partial in (False, True):
        law = PositionLaw(partial_frames=partial)
        for index in range(6):  # frames at rest (no move made), drifting 0.5 px per frame
            law.step(5.0 + 0.5 * index, 0.0, 0.0, 100.0, frame_interval_s=(index, index + 1.0), now_s=index + 1.05)
        moves.append(law.step(8.0, 0.0, 0.0, 100.0, frame_interval_s=(6.0, 7.0), now_s=7.05).move["x_um"])
        drifts.append(law.state[2])  # the drift it learned, px/s (x)
    assert drifts[0] == pytest.approx(drifts[1]) and drifts[0] > 0.2
    # Whole frames: the next one's middle 1.5 frames after the write (8.55 s); partial: the
    # middle of the rest of the scan in progress, from the write to its end at 8 s (7.525 s).
    ahead_px = drifts[0] * (8.55 - 7.525)
    less_px = (abs(moves[0]) - abs(moves[1])) / 0.1  # um -> px at 100 nm per pixel
    assert 0.6 * ahead_px < less_px <= 1.01 * ahead_px, "a frame's drift less (shortened by the law's caution)"


def test_in_the_simulated_lab_partial_frames_bring_the_position_law_to_the_target_sooner():
    start = (0.05 * 512 * 0.17692, 0.0)
    settings = loop.TimedSettings(time_budget_s=30.0)
    whole = loop.run_timed_trial("optimal", "position", start, seed=601, settings=settings)
    partial = loop.run_timed_trial("optimal", "position", start, seed=601,
                                   settings=loop.TimedSettings(time_budget_s=30.0, partial_frames=True))
    assert whole["outcome"] == partial["outcome"] == "converged"
    assert partial["true_error_px"] < 0.1
    assert any(record.get("first_row") for record in partial["records"])
    assert not any(record.get("first_row") for record in whole["records"])
    assert partial["frames_scanned"] < whole["frames_scanned"] and partial["seconds"] < whole["seconds"]


def test_the_estimator_uses_a_mask_taken_as_drawn_whole_and_an_anchored_one_partly():
    lasted = 256_000_000  # 256 rows, a row per millisecond
    for corners, anchored in (([[80, 60], [170, 60], [170, 200], [80, 200]], True),
                              ([[84, 60], [174, 60], [174, 200], [84, 200]], False)):
        core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE")
        core.process(timed_frame(shaded_part(), 0, 0, lasted))
        core.teach_mask(polygon=corners)
        assert core.estimator.mask_anchored is anchored
        core.moved(lasted + 40_000_000)
        landed = shaded_part((2.0, 1.0))
        landed[:40] = shaded_part((0.5, 0.0))[:40]  # the stage still moving
        estimate = core.process(timed_frame(landed, 1, lasted, lasted))
        if anchored:
            # The cut moves over the object with it: a pixel's move reads a tenth of a pixel
            # off (as a stage's gain off by a tenth would); the target itself reads zero.
            assert estimate.first_row == 64 and abs(estimate.dx_px - 2.0) < 0.15 and abs(estimate.dy_px - 1.0) < 0.15
            core.moved(2 * lasted + 40_000_000)
            at_rest = core.process(timed_frame(shaded_part(), 2, 2 * lasted, lasted))
            assert at_rest.first_row == 64 and abs(at_rest.dx_px) < 0.01 and abs(at_rest.dy_px) < 0.01
        else:
            assert estimate.first_row == 0 and core.counters["partial_frames_refused"] == 1
