"""The estimator's core without sockets: teaching from averaged frames."""

from __future__ import annotations

import numpy as np
import pytest

from semservo.wire import Frame, frame_header
from services.estimator.core import EstimatorCore, TeachError


def frame(pixels: np.ndarray, seq: int, pixel_size_nm: float = 100.0) -> Frame:
    return Frame(frame_header(pixels, seq=seq, acquired_at_ns=seq, pixel_size_nm=pixel_size_nm,
                              magnification=1000.0, dwell_ns=720.0, source="test"), pixels)


def scene(shift: float, noise_seed: int) -> np.ndarray:
    """A 128 x 128 texture (smoothed white noise, contrast 50 about 100) moved right by
    ``shift`` px (exactly, in Fourier space), under heavy pixel noise (sigma 40: ~2 dB)."""
    rng = np.random.default_rng(7)
    base = np.real(np.fft.ifft2(np.fft.fft2(rng.normal(0, 1, (160, 160)))
                                * np.exp(-2 * np.pi**2 * 2.0**2 * (np.fft.fftfreq(160)[:, None] ** 2
                                                                   + np.fft.fftfreq(160)[None, :] ** 2))))
    base = 100 + 50 * base / base.std()
    moved = np.real(np.fft.ifft2(np.fft.fft2(base) * np.exp(-2j * np.pi * np.fft.fftfreq(160)[None, :] * shift)))
    clean = moved[16:144, 16:144]
    return (clean + np.random.default_rng(noise_seed).normal(0, 40, clean.shape)).astype(np.float32)


def test_a_reference_averaged_over_frames_is_their_mean_and_less_noisy():
    core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE")
    frames = [frame(scene(0.0, seed), seq) for seq, seed in enumerate(range(8))]
    for each in frames:
        core.process(each)
    taught = core.teach_latest(frames=8)
    assert taught["frames_averaged"] == 8 and taught["frame_seq"] == 7
    # Eight frames average the noise down by sqrt(8): new noisy frames are estimated
    # more sharply, and more confidently, against the averaged reference than against a
    # single frame.
    def errors_and_confidences(first_seq: int):
        motions = [core.process(frame(scene(0.5, 100 + index), first_seq + index)) for index in range(10)]
        return ([np.hypot(motion.dx_px - 0.5, motion.dy_px) for motion in motions],
                [motion.confidence for motion in motions])

    averaged, averaged_confidence = errors_and_confidences(8)
    core.process(frame(scene(0.0, 50), 30))  # one unmoved frame, taught alone
    core.teach_latest(frames=1)
    single, single_confidence = errors_and_confidences(31)
    assert np.mean(averaged) < 0.04 and max(averaged) < 0.15
    assert np.mean(averaged) < 0.75 * np.mean(single)
    assert min(averaged_confidence) >= 0.5 and np.mean(averaged_confidence) > np.mean(single_confidence)


def test_averaging_asks_for_frames_that_exist_and_share_one_scan():
    core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE")
    with pytest.raises(TeachError, match="no frame"):
        core.teach_latest()
    core.process(frame(scene(0, 1), 0))
    with pytest.raises(TeachError, match="only 1 frames"):
        core.teach_latest(frames=4)
    core.process(frame(scene(0, 2), 1, pixel_size_nm=50.0))
    with pytest.raises(TeachError, match="scan changed"):
        core.teach_latest(frames=2)
    assert core.reference is None  # nothing half-done


def test_a_run_that_cannot_turn_switches_rotation_off_and_back():
    import cv2

    from semservo.estimation import rotate_about_centre

    texture = cv2.GaussianBlur(np.random.default_rng(3).normal(0, 1, (256, 256)).astype(np.float32), (0, 0), 2)
    core = EstimatorCore(rotation=True, fft_effort="FFTW_ESTIMATE")
    core.process(frame(texture, 0))
    core.teach_latest()
    turned = rotate_about_centre(texture, 5.0)  # content turned: measured only when asked
    assert core.measure(False) == {"rotation": False, "tilts": False}
    assert core.process(frame(turned, 1)).rotation_deg == 0.0
    assert core.measure(None) == {"rotation": True, "tilts": False}  # back to the configuration
    assert core.process(frame(turned, 2)).rotation_deg == pytest.approx(5.0, abs=0.3)


def test_rotation_cannot_be_asked_of_an_estimator_configured_without_it():
    core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE")
    with pytest.raises(TeachError, match="rotation is off"):
        core.measure(True)
    assert core.measure(False) == {"rotation": False, "tilts": False}


def test_tilts_are_measured_against_the_taught_sweep_and_refused_without_one():
    from tests.unit.test_tilt import KERNEL, PIXEL_UM, SIZE, WORKING_DISTANCES_UM, sweep_of_plane, texture

    core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE")
    core.process(frame(texture().astype(np.float32), 0, pixel_size_nm=PIXEL_UM * 1000))
    core.teach_latest()
    with pytest.raises(TeachError, match="teach with tilts=true"):
        core.measure(None, tilts=True)
    with pytest.raises(TeachError, match="cannot tell the tilts"):  # a featureless sweep is refused
        core.teach_tilt(sweep_of_plane(1.0, 1.0, scene=np.full((SIZE, SIZE), 120.0)), list(WORKING_DISTANCES_UM),
                        PIXEL_UM * 1000)
    taught = core.teach_tilt(sweep_of_plane(1.0, -1.0), list(WORKING_DISTANCES_UM), PIXEL_UM * 1000)
    assert taught["tilt"]["alpha_deg"] == pytest.approx(1.0, abs=0.3)
    assert core.measure(None, tilts=True)["tilts"] is True
    measured = core.tilt_from_sweep(sweep_of_plane(4.0, -3.0), list(WORKING_DISTANCES_UM), PIXEL_UM * 1000,
                                    scan_started_at_ns=5)
    # Against the taught sweep: (4 - 1, -3 - -1) degrees.
    assert measured["alpha_deg"] == pytest.approx(3.0, abs=0.3) and measured["beta_deg"] == pytest.approx(-2.0, abs=0.3)
    assert measured["confidence"] > 0.5 and len(measured["depth_map_um"]) == SIZE // KERNEL
    estimate = core.process(frame(texture().astype(np.float32), 1, pixel_size_nm=PIXEL_UM * 1000))
    assert estimate.tilt_seq == measured["tilt_seq"] and estimate.alpha_deg == measured["alpha_deg"]
    # The sweep's own standard errors go with it: the controller weighs sweeps by them.
    assert estimate.tilt_uncertainty_deg == (measured["alpha_uncertainty_deg"], measured["beta_uncertainty_deg"])
    assert 0 < estimate.tilt_uncertainty_deg[0] < 0.3
    core.teach_latest()  # a new reference needs its own sweep
    assert core.tilt_reference is None


@pytest.mark.parametrize("precision, rotation", [("full", False), ("full", True), ("fast", True)])
def test_a_scene_with_nothing_to_register_is_refused_and_never_moves_the_stage(precision, rotation):
    """A featureless sample (a flat grey under shot noise: each scan is fresh noise, no
    content to register): every estimate against it is refused for its low confidence,
    whatever shift it reads, and the controller holds each one, then ends the run as
    scene lost, without a single move."""
    from collections import deque

    from semservo.control import ControlLaw
    from semservo.pairs import poisson_gaussian
    from semservo.protocol.controller import RunSettings
    from services.controller.run import Run, gate

    rng = np.random.default_rng(23)
    flat = np.full((256, 256), 120.0)
    core = EstimatorCore(rotation=rotation, precision=precision, fft_effort="FFTW_ESTIMATE")
    core.process(frame(poisson_gaussian(flat, 200, 2.0, rng).astype(np.float32), 0))
    core.teach_latest()
    settings = RunSettings(lost_after=8)
    run = Run(id="r", reference_id=core.reference.id, settings=settings, started_at_ns=0, stage_at_start={},
              law=ControlLaw(("x", "y")), recent=deque())
    estimates = [core.process(frame(poisson_gaussian(flat, 200, 2.0, rng).astype(np.float32), seq))
                 for seq in range(1, 9)]
    verdicts = [gate(run, estimate) for estimate in estimates]
    assert max(estimate.confidence for estimate in estimates) < settings.min_confidence
    assert max(np.hypot(estimate.dx_px, estimate.dy_px) for estimate in estimates) > 1.0  # the reading is noise
    assert all(verdict is not None and verdict.action == "held: low confidence" for verdict in verdicts)
    assert [verdict.ending for verdict in verdicts] == [None] * 7 + ["failed"]
    assert "scene lost" in verdicts[-1].reason and run.iterations == 0


def test_a_mask_upload_keeps_every_row_even_where_it_looks_like_a_data_bar():
    """A mask whose part reaches the bottom edge: its last rows are full-scale white over
    a black row, the look of a vendor's text overlay, and an upload read as an SEM image
    loses them. A mask has no data bar: the teach reads it whole (the positioning
    benchmark's Otsu mask of a live frame was refused as 512 x 501 against 512 x 512)."""
    import base64
    import io

    from PIL import Image

    from semservo.protocol.estimator import TeachRequest
    from services.estimator.commands import teach
    from services.estimator.core import decode_upload

    mask = np.zeros((128, 128), np.uint8)
    mask[40:, 30:70] = 255  # the part, down to the bottom edge
    mask[120:, ::3] = 255  # with bright specks in the last rows
    buffer = io.BytesIO()
    Image.fromarray(mask).save(buffer, format="PNG")
    encoded = base64.b64encode(buffer.getvalue()).decode()
    assert decode_upload(encoded).shape[0] < 128  # read as an SEM picture: a "data bar" cropped
    core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE")
    core.process(frame(scene(0.0, 1), 0))

    class Estimator:  # what the handler reads: the core, and no focus sweeps
        tracker = None

        def __init__(self, core):
            self.core = core

        def taught(self, reference):
            return reference

    reply = teach(Estimator(core), TeachRequest(mask_b64=encoded))
    assert core.describe_reference()["kind"] == "mask" and reply is not None


def test_a_teach_whose_sweep_pins_the_tilts_loosely_sweeps_again_and_pools_them():
    from services.estimator.core import NoTiltReference, TiltSettings
    from tests.unit.test_tilt import PIXEL_UM, WORKING_DISTANCES_UM, plane_depths, sweep_of_depths, texture

    core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE", tilt=TiltSettings(teach_sweeps=4))
    core.process(frame(texture().astype(np.float32), 0, pixel_size_nm=PIXEL_UM * 1000))
    core.teach_latest()
    # A faint texture: one sweep pins the tilts to +-0.12-0.16 degree only (refused alone).
    faint = 100 + 3.5 * (texture() - 100) / 60
    distances = list(WORKING_DISTANCES_UM)
    answers = []
    for seed in range(10):
        answers.append(core.teach_tilt(sweep_of_depths(plane_depths(2.0, -1.0), faint, seed), distances,
                                       PIXEL_UM * 1000))
        if answers[-1] is not None:
            break
        pool = core.teach_pool
        assert pool.estimate.sweeps == len(answers) and core.tilt_reference is None  # not taught yet
    taught = answers[-1]
    assert answers[0] is None and 1 < len(answers) <= 4
    tilt = taught["tilt"]
    assert tilt["sweeps"] == len(answers) and max(tilt["alpha_uncertainty_deg"], tilt["beta_uncertainty_deg"]) < 0.1
    assert tilt["alpha_deg"] == pytest.approx(2.0, abs=0.3) and tilt["beta_deg"] == pytest.approx(-1.0, abs=0.3)
    assert core.tilt_reference is not None and core.teach_pool is None
    # Runs measure against the pooled reference.
    assert core.measure(None, tilts=True)["tilts"] is True

    # A texture too faint to pin them in four sweeps: refused, with how well after how many; bounded.
    core.measure(None, tilts=False)
    core.teach_latest()
    fainter = 100 + 1.5 * (texture() - 100) / 60
    calls = 0
    refused = r"cannot tell the tilts: .*(pin the tilts to \+-|clear focus peak)"
    with pytest.raises(NoTiltReference, match=refused) as refusal:
        for seed in range(10):
            calls += 1
            core.teach_tilt(sweep_of_depths(plane_depths(2.0, -1.0), fainter, seed), distances, PIXEL_UM * 1000)
    assert calls <= 4 and core.tilt_reference is None and core.teach_pool is None
    assert calls == 1 or f"{calls} focus sweeps" in str(refusal.value)


def test_a_teach_the_wide_sweeps_cannot_pin_sweeps_finely_about_the_depths_they_found():
    """A faint texture one wide sweep pins to +-0.08-0.11 degree only (the teach keeps at
    most +-0.071): the teach goes on with sweeps at a quarter of a depth of field on the
    wide sweep's grid, about the depths it found, pools those, and runs sweep that grid."""
    from services.estimator.core import NoTiltReference, TiltSettings
    from tests.unit.test_tilt import PIXEL_UM, WORKING_DISTANCES_UM, plane_depths, sweep_of_depths, texture

    settings = TiltSettings(teach_sweeps=1, fine_teach_sweeps=4, depth_of_field_um=0.5)
    core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE", tilt=settings)
    core.process(frame(texture().astype(np.float32), 0, pixel_size_nm=PIXEL_UM * 1000))
    core.teach_latest()
    faint = 100 + 3.5 * (texture() - 100) / 60
    depths = plane_depths(2.0, -1.0)
    wide = list(WORKING_DISTANCES_UM)
    assert core.teach_tilt(sweep_of_depths(depths, faint, 0), wide, PIXEL_UM * 1000) is None
    fine = core.next_sweep()
    assert fine == list(core.teach_pool.fine_sweep) and core.teach_pool.estimate is None
    wide_step, fine_step = wide[1] - wide[0], fine[1] - fine[0]
    assert fine_step == pytest.approx(wide_step / 2)  # a quarter of 0.5 um: half the wide step
    assert (np.abs(np.round((np.array(fine) - wide[0]) / fine_step) * fine_step + wide[0] - fine) < 1e-9).all()
    assert fine[0] <= depths.min() - 2 * 0.5 + 1e-9 and fine[-1] >= depths.max() + 2 * 0.5 - 1e-9
    assert len(fine) < 2 * len(wide) - 1  # only the depths the kernels are at
    taught = None
    for seed in range(1, 5):
        taught = core.teach_tilt(sweep_of_depths(depths, faint, seed, fine), core.next_sweep(), PIXEL_UM * 1000)
        if taught is not None:
            break
    tilt = taught["tilt"]
    assert tilt["fine"] is True and tilt["wide_sweeps"]["sweeps"] == 1 and 1 <= tilt["sweeps"] <= 4
    assert max(tilt["wide_sweeps"]["alpha_uncertainty_deg"], tilt["wide_sweeps"]["beta_uncertainty_deg"]) > 0.071
    assert max(tilt["alpha_uncertainty_deg"], tilt["beta_uncertainty_deg"]) <= 0.071
    assert tilt["alpha_deg"] == pytest.approx(2.0, abs=0.2) and tilt["beta_deg"] == pytest.approx(-1.0, abs=0.2)
    assert core.tilt_reference.grid == pytest.approx((fine[0], fine_step)) and core.teach_pool is None
    # A run's sweeps sample the fine grid (its pull between samples, the teach's, cancels at the goal).
    core.last_tilt = {"confidence": 1.0, "absolute_alpha_deg": 2.0, "absolute_beta_deg": -1.0,
                      "centre_um": tilt["centre_um"]}  # near the taught pose
    run_sweep = np.array(core.next_sweep())
    on_grid = (run_sweep - fine[0]) / fine_step
    assert np.allclose(on_grid, np.round(on_grid)) and np.allclose(np.diff(run_sweep), fine_step)

    # A run's coarser sweep that cannot pin the tilts is followed by a fine one about its depths.
    run_depths = core.sweep_depths(sweep_of_depths(depths, faint, 7), wide, PIXEL_UM * 1000)
    follow = core.fine_sweep_after([run_depths], wide, PIXEL_UM * 1000)
    assert follow is not None and np.allclose(np.diff(follow), fine_step)
    assert np.allclose((np.array(follow) - fine[0]) / fine_step, np.round((np.array(follow) - fine[0]) / fine_step))
    assert core.fine_sweep_after([run_depths], follow, PIXEL_UM * 1000) is None  # already fine
    # Its fine sweeps are pooled up to as many as the teach's (4 here), a coarse one's up to teach_sweeps (1).
    assert not core.sweep_again([run_depths], wide, PIXEL_UM * 1000)
    fine_depths = core.sweep_depths(sweep_of_depths(depths, 100 + 2.2 * (texture() - 100) / 60, 8, follow), follow,
                                    PIXEL_UM * 1000)
    assert core.sweep_again([fine_depths], follow, PIXEL_UM * 1000)

    # Too faint for the fine sweeps too: refused, saying it swept both ways; never a third way.
    core.measure(None, tilts=False)
    core.teach_latest()
    fainter = 100 + 2.0 * (texture() - 100) / 60
    assert core.teach_tilt(sweep_of_depths(depths, fainter, 0), wide, PIXEL_UM * 1000) is None
    with pytest.raises(NoTiltReference, match=r"1 wide focus sweep and \d fine cannot tell the tilts"):
        for seed in range(1, 10):
            plan = core.next_sweep()
            core.teach_tilt(sweep_of_depths(depths, fainter, seed, plan), plan, PIXEL_UM * 1000)
    assert core.tilt_reference is None and core.teach_pool is None


def test_a_teach_with_fine_sweeps_off_is_refused_where_the_wide_ones_cannot_pin_the_tilts():
    from services.estimator.core import NoTiltReference, TiltSettings
    from tests.unit.test_tilt import PIXEL_UM, WORKING_DISTANCES_UM, plane_depths, sweep_of_depths, texture

    core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE",
                         tilt=TiltSettings(teach_sweeps=1, fine_teach_sweeps=0, depth_of_field_um=0.5))
    core.process(frame(texture().astype(np.float32), 0, pixel_size_nm=PIXEL_UM * 1000))
    core.teach_latest()
    faint = 100 + 3.5 * (texture() - 100) / 60
    with pytest.raises(NoTiltReference, match=r"the reference's focus sweep cannot tell the tilts: .*pin the tilts"):
        core.teach_tilt(sweep_of_depths(plane_depths(2.0, -1.0), faint, 0), list(WORKING_DISTANCES_UM),
                        PIXEL_UM * 1000)
    # A reference the wide sweeps taught: its runs' sweeps are never swapped for fine ones.
    core.teach_latest()
    assert core.teach_tilt(sweep_of_depths(plane_depths(2.0, -1.0)), list(WORKING_DISTANCES_UM), PIXEL_UM * 1000)
    assert core.tilt_reference.fine is False
    loose = core.sweep_depths(sweep_of_depths(plane_depths(2.0, -1.0), faint, 3), list(WORKING_DISTANCES_UM),
                              PIXEL_UM * 1000)
    assert core.fine_sweep_after([loose], list(WORKING_DISTANCES_UM), PIXEL_UM * 1000) is None


def test_a_new_reference_does_not_pool_the_sweeps_of_the_one_before():
    from tests.unit.test_tilt import PIXEL_UM, WORKING_DISTANCES_UM, plane_depths, sweep_of_depths, texture

    core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE")
    core.process(frame(texture().astype(np.float32), 0, pixel_size_nm=PIXEL_UM * 1000))
    core.teach_latest()
    faint = 100 + 3.5 * (texture() - 100) / 60
    assert core.teach_tilt(sweep_of_depths(plane_depths(2.0, -1.0), faint, 0), list(WORKING_DISTANCES_UM),
                           PIXEL_UM * 1000) is None
    core.teach_latest()  # a new reference: its tilts need sweeps of their own
    assert core.teach_pool is None
    core.teach_tilt(sweep_of_depths(plane_depths(2.0, -1.0), faint, 1), list(WORKING_DISTANCES_UM), PIXEL_UM * 1000)
    assert core.teach_pool is None or core.teach_pool.estimate.sweeps == 1


def test_a_run_pools_sweeps_that_cannot_pin_the_tilts_or_pin_them_loosely_near_the_goal():
    from tests.unit.test_tilt import PIXEL_UM, WORKING_DISTANCES_UM, plane_depths, sweep_of_depths, texture

    core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE")
    core.process(frame(texture().astype(np.float32), 0, pixel_size_nm=PIXEL_UM * 1000))
    core.teach_latest()
    distances, pixel_nm = list(WORKING_DISTANCES_UM), PIXEL_UM * 1000
    assert core.teach_tilt(sweep_of_depths(plane_depths(2.0, -1.0)), distances, pixel_nm) is not None  # one sweep

    def depths(alpha: float, contrast: float, seed: int) -> np.ndarray:
        scene = 100 + contrast * (texture() - 100) / 60
        return core.sweep_depths(sweep_of_depths(plane_depths(alpha, -1.0), scene, seed), distances, pixel_nm)

    loose_near = depths(2.0, 4.0, 0)  # accepted alone (+-0.08 degree), at the taught tilts
    assert core.pooled_estimate([loose_near], distances, pixel_nm).confidence > 0
    assert core.sweep_again([loose_near], distances, pixel_nm)
    # Far from the goal, a loose sweep is acted on as it is: the next move is larger than its noise.
    assert not core.sweep_again([depths(4.0, 4.0, 0)], distances, pixel_nm)
    # Refused alone for its uncertainty: swept again wherever it is.
    refused = depths(4.0, 3.5, 1)
    assert core.pooled_estimate([refused], distances, pixel_nm).confidence == 0
    assert core.sweep_again([refused], distances, pixel_nm)
    # Never beyond the bound.
    assert not core.sweep_again([depths(2.0, 4.0, seed) for seed in range(4)], distances, pixel_nm)
    # The reported measurement pools them: fewer degrees of noise, and says how many sweeps.
    single = core.tilt_from_sweep(sweep_of_depths(plane_depths(2.0, -1.0), 100 + 4 * (texture() - 100) / 60, 3),
                                  distances, pixel_nm)
    pooled = core.tilt_from_sweep(sweep_of_depths(plane_depths(2.0, -1.0), 100 + 4 * (texture() - 100) / 60, 3),
                                  distances, pixel_nm, earlier=[loose_near, depths(2.0, 4.0, 1)])
    assert single["sweeps"] == 1 and pooled["sweeps"] == 3 and pooled["confidence"] > 0
    assert pooled["alpha_uncertainty_deg"] < 0.8 * single["alpha_uncertainty_deg"]
    assert abs(pooled["alpha_deg"]) < 0.3 and abs(pooled["beta_deg"]) < 0.3


def test_the_scan_averaged_setting_reaches_every_reference_the_core_installs():
    from semservo.config import EstimatorSettings

    assert EstimatorSettings().scan_averaged is True  # on unless the lab asks otherwise (semservo.estimation.raster)
    assert EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE").scan_averaged is True
    for averaged in (False, True):
        core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE", scan_averaged=averaged)
        core.process(frame(scene(0.0, 3), 0))
        core.teach_latest(frames=1)
        assert core.estimator.scan_averaged is averaged
        motion = core.process(frame(scene(0.5, 4), 1))
        assert abs(motion.dx_px - 0.5) < 0.1 and abs(motion.dy_px) < 0.1


def test_the_scan_averaged_shift_only_for_frames_scanned_slowly_enough_for_it_to_matter():
    """A frame scanned faster than raster.SCAN_AVERAGED_FROM_S keeps its whole-frame shift
    (no vibration moves so short a scan's rows apart, and the loop's latency at high frame
    rates stays low); how long the scan lasted comes from the frame's header: its dwell,
    its scan's start, or else the time since the frame before it. The estimate says which."""
    from semservo.estimation import MotionEstimator
    from semservo.estimation.raster import scan_lasted_s

    def header_frame(pixels, seq, acquired_at_ns, dwell_ns=None, scan_started_at_ns=None):
        header = frame_header(pixels, seq=seq, acquired_at_ns=acquired_at_ns, pixel_size_nm=100.0,
                              magnification=1000.0, dwell_ns=dwell_ns, source="test",
                              scan_started_at_ns=scan_started_at_ns)
        return Frame(header, pixels)

    core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE")
    core.process(header_frame(scene(0.0, 3), 0, 10**9, dwell_ns=720.0))
    core.teach_latest(frames=1)
    pixels = scene(0.5, 4)
    fast = core.process(header_frame(pixels, 1, 2 * 10**9, dwell_ns=720.0))  # 128 x 128 x 720 ns: 12 ms
    slow = core.process(header_frame(pixels, 2, 3 * 10**9, dwell_ns=5000.0))  # 82 ms
    assert not fast.scan_averaged and slow.scan_averaged
    assert abs(fast.dx_px - 0.5) < 0.1 and abs(slow.dx_px - 0.5) < 0.1
    assert fast.dx_px != slow.dx_px  # the refinement ran on one of them only
    started = core.process(header_frame(pixels, 3, 4 * 10**9, scan_started_at_ns=4 * 10**9 - 10**8))  # 100 ms
    assert started.scan_averaged
    started = core.process(header_frame(pixels, 3, 4 * 10**9, scan_started_at_ns=4 * 10**9 - 10**7))  # 10 ms
    assert not started.scan_averaged
    started = core.process(header_frame(pixels, 3, 4 * 10**9, scan_started_at_ns=4 * 10**9 - 10**8))
    assert started.scan_averaged
    # Nothing said but when it came: at most the time since the frame before it.
    assert not core.process(header_frame(pixels, 4, 4 * 10**9 + 5 * 10**6)).scan_averaged  # 5 ms later
    assert core.process(header_frame(pixels, 5, 5 * 10**9)).scan_averaged
    plain = MotionEstimator(scene(0.0, 3), rotation=False)  # made without it: asking for it is an error
    with pytest.raises(ValueError, match="without scan averaging"):
        plain.estimate(pixels, scan_averaged=True)
    assert scan_lasted_s((512, 512), acquired_at_ns=10**9) is None
    assert scan_lasted_s((512, 512), dwell_ns=100.0) == pytest.approx(0.0262144)
    # A simulated lab's own clock first, however fast it runs against the wall clock.
    assert scan_lasted_s((512, 512), source_interval_s=(2.0, 2.19), dwell_ns=100.0, scan_started_at_ns=0,
                         acquired_at_ns=10**7) == pytest.approx(0.19)


def test_a_sweep_that_cannot_tell_the_tilts_leaves_the_frames_undone_with_the_last_that_could():
    core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE")
    confident = {"alpha_deg": 2.0, "beta_deg": -1.5, "confidence": 0.9}
    failed = {"alpha_deg": None, "beta_deg": None, "confidence": 0.0}
    core.last_tilt = confident
    core.last_tilt = failed
    assert core.last_tilt is failed and core.undone_tilt is confident
    core.last_tilt = {"alpha_deg": 0.1, "beta_deg": 0.0, "confidence": 0.8}
    assert core.undone_tilt["alpha_deg"] == 0.1
    core.clear()  # a new reference's sweeps start afresh: nothing undone
    assert core.last_tilt is None and core.undone_tilt is None


def test_a_teach_learns_the_stages_vibration_lines_from_the_frames_at_rest_in_the_background():
    """The frames scanned after the stage settled (the gateway says when) teach the
    vibration's steady tones; the reference says what was learned, and each frame's
    scan-averaged shift then fits them. The frames here are made by resampling a texture
    row by row (not the simulated SEM), the scan's time from the frame's source clock."""
    import time as clock

    from scipy import ndimage

    from services.estimator.core import VIBRATION_FRAMES

    rng = np.random.default_rng(4)
    size, margin, scan_s = 192, 16, 0.4
    base = ndimage.gaussian_filter(rng.standard_normal((size + 2 * margin,) * 2), 2.0)
    rows = np.arange(size)
    base *= 0.1 + np.exp(-0.5 * ((np.arange(size + 2 * margin)[:, None] - margin - size / 4) / (size / 8)) ** 2)
    texture = (100 + 400 * base).astype(np.float64)

    def vibrating(seq: int, mean_x: float = 0.0):
        phase = rng.uniform(0, 2 * np.pi, 2)
        time = rows / size * scan_s
        shift_x = mean_x + 0.4 * np.sin(2 * np.pi * 11.0 * time + phase[0])  # 11 Hz: 4.4 cycles a scan
        shift_y = 0.3 * np.cos(2 * np.pi * 11.0 * time + phase[1])
        grid_r, grid_c = np.mgrid[0:size, 0:size].astype(np.float64)
        pixels = ndimage.map_coordinates(texture, [grid_r + margin - shift_y[:, None], grid_c + margin - shift_x[:, None]],
                                         order=3, mode="reflect").astype(np.float32)
        header = frame_header(pixels, seq=seq, acquired_at_ns=10**9 * (seq + 1), pixel_size_nm=100.0,
                              magnification=1000.0, dwell_ns=None, source="test",
                              scan_started_at_ns=10**9 * (seq + 1) - int(scan_s * 1e9))
        header = header.model_copy(update={"source_interval_s": (seq * 0.5, seq * 0.5 + scan_s)})
        return Frame(header, pixels), float(shift_x.mean())

    core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE")
    for seq in range(VIBRATION_FRAMES):
        core.process(vibrating(seq)[0])
    taught = core.teach_latest(frames=1, scanned_after_ns=1)
    assert taught["vibration"]["state"] == "learning" and taught["vibration"]["frames"] == VIBRATION_FRAMES
    deadline = clock.monotonic() + 60
    while core.describe_reference()["vibration"]["state"] == "learning" and clock.monotonic() < deadline:
        clock.sleep(0.05)
    vibration = core.describe_reference()["vibration"]
    assert vibration["state"] == "learned" and any(abs(line - 11.0) < 0.5 for line in vibration["lines_hz"])
    assert len(core.estimator.vibration_hz) == len(vibration["lines_hz"]) >= 1
    errors = []
    for seq in range(VIBRATION_FRAMES, VIBRATION_FRAMES + 4):
        moved, truth = vibrating(seq, mean_x=1.25)
        estimate = core.process(moved)
        assert estimate.scan_averaged
        errors.append(abs(estimate.dx_px - truth))
    assert max(errors) < 0.05
    # Without the stage's settling time only the frames averaged are known to be at rest:
    # one frame teaches no lines, and the reference says why.
    core.teach_latest(frames=1)
    assert core.describe_reference()["vibration"] == {"state": "none", "lines_hz": [], "frames": 1,
                                                      "reason": "fewer than 2 frames at rest"}
    off = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE", vibration_lines=False)
    for seq in range(3):
        off.process(vibrating(seq)[0])
    assert off.teach_latest(frames=3)["vibration"]["reason"] == "vibration lines are off (settings)"
    assert off.estimator.vibration_hz == ()


def test_a_sweep_measured_against_a_loosely_taught_plane_is_refused_when_both_together_miss_the_line():
    """A teach pooled from faint sweeps, pinned to several hundredths of a degree: a
    sweep that would be measured alone (+-0.07-0.08) is not, against it, for the two
    standard errors together are over 0.1 degree; the tracker is told to sweep it again,
    and a sweep pinned tightly is measured."""
    from services.estimator.core import TiltSettings
    from tests.unit.test_tilt import PIXEL_UM, WORKING_DISTANCES_UM, plane_depths, sweep_of_depths, texture

    core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE", tilt=TiltSettings(teach_sweeps=4))
    core.process(frame(texture().astype(np.float32), 0, pixel_size_nm=PIXEL_UM * 1000))
    core.teach_latest()
    distances, pixel_nm = list(WORKING_DISTANCES_UM), PIXEL_UM * 1000
    faint = 100 + 3.5 * (texture() - 100) / 60
    for seed in range(4):
        if core.teach_tilt(sweep_of_depths(plane_depths(2.0, -1.0), faint, seed), distances, pixel_nm) is not None:
            break
    taught = core.tilt_reference.estimate
    taught_worst = max(taught.alpha_uncertainty_deg, taught.beta_uncertainty_deg)
    assert 0.05 < taught_worst < 0.1
    loose_sweep = sweep_of_depths(plane_depths(2.0, -1.0), 100 + 4 * (texture() - 100) / 60, 7)
    loose = core.sweep_depths(loose_sweep, distances, pixel_nm)
    alone = core.pooled_estimate([loose], distances, pixel_nm)
    alone_worst = max(alone.alpha_uncertainty_deg, alone.beta_uncertainty_deg)
    assert alone.confidence > 0 and np.hypot(alone_worst, taught_worst) > 0.1  # measured alone, not against it
    measured = core.tilt_from_sweep(loose_sweep, distances, pixel_nm, sweep_depth_map=loose)
    assert measured["confidence"] == 0.0 and measured["alpha_deg"] is None and "taught plane" in measured["reason"]
    assert core.sweep_again([loose], distances, pixel_nm)
    measured = core.tilt_from_sweep(sweep_of_depths(plane_depths(2.0, -1.0), seed=8), distances, pixel_nm)
    assert measured["confidence"] > 0 and abs(measured["alpha_deg"]) < 0.3


def test_the_estimator_reads_every_sweep_by_the_focus_measure_it_was_set_to(monkeypatch):
    """SEMSERVO_ESTIMATOR__TILT_FOCUS_MEASURE: the setting reaches the core, which reads
    the taught sweep and the run's alike by it (the depths are the library's for that
    measure); an unknown measure is refused when the settings are read."""
    from pydantic import ValidationError

    from semservo.config import Settings
    from semservo.estimation.tilt import kernel_depths
    from services.estimator.core import TiltSettings
    from tests.unit.test_tilt import PIXEL_UM, WORKING_DISTANCES_UM, sweep_of_plane

    monkeypatch.setenv("SEMSERVO_ESTIMATOR__TILT_FOCUS_MEASURE", "gradient")
    assert Settings().estimator.tilt_focus_measure == "gradient"
    monkeypatch.setenv("SEMSERVO_ESTIMATOR__TILT_FOCUS_MEASURE", "sobel")
    with pytest.raises(ValidationError, match="gradient"):
        Settings()
    sweep, distances = sweep_of_plane(2.0, -1.0), list(WORKING_DISTANCES_UM)
    for measure in ("normalized_variance", "gradient"):
        core = EstimatorCore(rotation=False, fft_effort="FFTW_ESTIMATE", tilt=TiltSettings(focus_measure=measure))
        read = core.sweep_depths(sweep, distances, PIXEL_UM * 1000)
        np.testing.assert_array_equal(read.depths, kernel_depths(sweep, distances, 32, PIXEL_UM, measure=measure).depths)
    assert not np.array_equal(read.depths, kernel_depths(sweep, distances, 32, PIXEL_UM).depths)


def test_the_wire_knows_the_same_focus_measures_as_the_science():
    """The settings, the wire's and the API's TiltTeach take FocusMeasure; the science
    keeps its own list (it imports no wire types): the two stay the same."""
    from typing import get_args

    from semservo.estimation.tilt import FOCUS_MEASURES
    from semservo.protocol.estimator import FocusMeasure

    assert get_args(FocusMeasure) == FOCUS_MEASURES
